"""nodlidar."""
