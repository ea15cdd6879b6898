"""Live views of a running sensor: the growing 3D cloud, the mirrors and the tracks over
the Foxglove WebSocket protocol (and the same stream to an MCAP file).

:mod:`nodlidar.live.encode` turns clouds, mirror patches, the nod and tracks into Foxglove
messages (pure functions); :mod:`nodlidar.live.view` runs a runtime session and publishes
them. ``foxglove`` (foxglove-sdk) is imported only by the functions that need it.
"""
