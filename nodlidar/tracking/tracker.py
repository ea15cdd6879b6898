"""Multi-object tracker: a constant-velocity Kalman filter per track, gating, global
nearest-neighbour assignment, birth, confirmation and deletion.

Each scan's dynamic clusters (:class:`~nodlidar.tracking.segment.Segmented`; a
:class:`~nodlidar.tracking.scans.ScanPoints` from the live path is segmented first by the
tracker's own :class:`~nodlidar.tracking.segment.OnlineSegmenter`) are the measurements.
Every track carries a constant-velocity state ``(x, vx, y, vy)`` filtered over time with
Stone Soup's components (:class:`~stonesoup.models.transition.linear.ConstantVelocity` per
axis, :class:`~stonesoup.predictor.kalman.KalmanPredictor`,
:class:`~stonesoup.updater.kalman.KalmanUpdater`). Per scan:

1. **predict** every track to the cluster's mean beam time;
2. **gate**: a cluster can go to a track only within ``gate_m`` of its predicted position
   and within the chi-square gate ``gate_chi2`` of the position innovation;
3. **assign** globally (GNN: :func:`scipy.optimize.linear_sum_assignment` on the pairs'
   negative log-likelihoods, ``d^2 + ln det S`` up to a constant, ungated pairs forbidden;
   ``assign_likelihood``) - the joint assignment with the least total cost, not the
   greedy closest pair first, which swaps two objects that pass close by. A
   cluster that other confirmed tracks' predictions also fall on (within ``share_m`` of its
   points) is shared: each point goes to the nearest prediction (two people touching in the
   top view in one scan);
4. clusters left over within ``merge_m`` of a track's assigned cluster are pieces of it (an
   object seen through two mirror windows can come apart in one scan) and join it, as do
   those within ``merge_hidden_m`` whose gap to it a nearer object hid (a box behind a
   person, cut in two by the person's shadow);
5. the rest start *tentative* tracks (leftovers within ``merge_m`` of each other: one
   track), *confirmed* once seen in ``confirm_scans`` scans and surely moving at
   ``confirm_speed_m_s`` or more (a pole, a table's edge or a person standing still,
   dynamic before static support can judge them, stays tentative); of two tracks updated in the
   same scan within ``coalesce_m`` of each other (one object followed twice) the younger ends
   (not when both were followed six scans or more and the scan saw their objects apart:
   ``coalesce_seen_apart``), and so does the younger of two that split one cluster between
   them in ``shared_scans`` sightings in a row, moving alike and never seen apart (a box
   that got a second track);
   a track unseen for more than ``max_missed`` scans ends (the default 25 outlasts the nod's
   blind interval, ~8 scans on the paper's ramp, and one person walking behind another:
   16 scans in ``design/scenes/track-crossing.toml``; the track coasts on its prediction),
   and up to ``occluded_scans`` more while its predicted place is hidden behind another
   track's object.
   A track seen in one scan only (no velocity) may, with ``reacquire_speed_m_s``, take a
   cluster farther than ``gate_m`` after a gap (opt-in; :class:`TrackerConfig`). A moving
   track whose object turned (``turn_reach_m``: outside the constant-velocity gate but near
   where it was last seen) keeps its identity and starts its motion afresh. A moving
   track may also take a cluster that static support made consistent when that support is
   the tracks' own earlier points (``follow_supported_m_s``: its object back on its path).
   A track that took nothing may take the nearest cluster that is not dynamic but has a
   few inconsistent points, fewer than a birth needs (``follow_inconsistent_fraction``).
   A new object that only a lost moving track could be (it turned while unseen, beyond
   every gate) continues that track once the two motions meet (``stitch_turned_m``; also
   when it stopped on its way, or stood still and walked off: ``stitch_stopped``). A track
   whose object stops, starts or turns within its gates (its uncut centroids' speed more
   than halved or doubled, or their heading turned at one speed, and its latest sightings'
   own estimate agreeing) restarts its motion from the sightings since (``maneuver_m_s``,
   ``maneuver_turn_deg``).

The measurement of a track in a scan is the ground-plane centroid of its points and, from
the second scan on, the velocity from the entropy refinement (:func:`refine_motion`, eqs
11-13) over the track's last ``window_scans`` scans, warm-started from the previous one
(search half-width ``warm_search_m_s``, and for the voxel entropy a coarser grid,
``warm_voxel_grid``); the Rényi sum uses every point of the window and at most as many
pairs as ``max_points`` points have (``renyi_subsample``), each weighted by its incidence
and, where a window's edge cuts the object's slice, by the speed across that edge
(``window_cut_speed_m_s``); Newton's minimiser gathers its pairs again where its minimum
leaves the region they were gathered for (``newton_recentre``). Where a window is cut and a
moving circle explains it (``round_model``), the circle's velocity is fused with the
entropy's, and the fused covariance is the measurement's (``round_fuse``,
``round_filter_cov``). The velocity enters the filter with its calibrated covariance
inflated by the window's overlap with the previous one, the birth prior forgotten at the
first estimate (``velocity_fusion="overlap"``). The reported state (position, speed,
heading, covariance of ``(x, y, vx, vy)``) is the filter's.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from ..errors import require
from .motion import (
    MotionEstimate,
    coarse_motion,
    incidence_weights,
    motion_from_velocity,
    refine_motion,
    smooth_along_scan,
)
from .round_motion import fit_moving_circle
from .segment import (
    behind_or_through,
    column_rays,
    cut_edges,
    hidden_between,
    seen_apart,
    seen_through,
    silhouette_ends,
)
from .voxels import unique_keys

if TYPE_CHECKING:
    from .scans import ScanPoints
    from .segment import OnlineSegmenter, SegmentConfig, Segmented

__all__ = ["TrackerConfig", "TrackState", "Tracker", "FUSIONS", "stone_soup_time"]

#: ``TrackerConfig.velocity_fusion`` choices
FUSIONS = ("kalman", "window", "first", "overlap")


@dataclass(frozen=True)
class TrackerConfig:
    """Tracker parameters (see the module docstring).

    Attributes
    ----------
    gate_m : float
        Largest distance [m] from a track's predicted position to a cluster it may take.
    gate_chi2 : float
        Chi-square gate on the position innovation (2 dof; 13.8 = 99.9 %).
    merge_m : float
        Clusters left over within this of a track's assigned cluster join it, and new
        clusters within it of each other are one new object [m] (about an object's size:
        the faces of a 0.4 m box seen through different windows are 0.35 m apart; below
        the 0.42 m between two people side by side).
    share_m : float
        A cluster is shared with another confirmed track whose prediction lies within this
        of its points [m].
    assign_likelihood : bool
        The assignment's pair cost is the negative log-likelihood of the cluster's centroid
        under the track's prediction, ``d^2 + ln(det S / sigma^4)`` (``S`` the innovation
        covariance, ``sigma`` = ``position_sigma_m``: 0 for a sure prediction), not the
        squared Mahalanobis distance ``d^2`` alone. A vague prediction (a young track's
        two-scan velocity carried over the nod's blind part: position sd 0.3-0.4 m) is near
        anything in its own sigmas; by ``d^2`` alone it won the one cluster of the scan
        from the sure track (sd 0.04 m) whose object it was, was coalesced into it, and its
        own object got a second track. Measured, seeds 0-7: two people side by side on the
        diagonal (``design/scenes/track-side-by-side-diagonal.toml``) 2 identity switches
        -> 0 with mirrors; four people P2 2 -> 0; the box (``track-box.toml``) with
        mirrors 4 -> 2; false tracks over every scene 216 -> 210; nothing worse by the
        issue's criteria (docs/tracking.md "A vague prediction does not win a sure track's
        cluster"). False: ``d^2`` alone.
    coalesce_m : float
        Of two tracks updated in one scan closer than this [m], the younger ends (below
        the 0.42 m between two people side by side).
    coalesce_seen_apart : bool
        Two tracks within ``coalesce_m`` whose clusters of this scan the scan saw apart
        (:func:`~nodlidar.tracking.segment.seen_apart`) follow two objects: neither ends.
        Their filtered positions can meet while their objects do not: two people walking
        towards each other who meet 0.5 m apart and turn to walk on together, each
        filter carrying its track on past the turn (``design/scenes/track-meet.toml``:
        the younger track ended and its person got a new one; measured without it, seeds
        0-7, mirrors / lifted, 8 / 8 switches before ``maneuver_turn_deg``'s restart
        took the lagging line fit (:func:`_agrees`), 0 / 5 after, and over the meeting
        scenes of ``benchmarks/heldout`` with it 9 / 10 against 2 / 4). Only tracks
        followed six scans or more each: a piece of one person that a noisy beam split
        off, seen apart from the rest, is a new track of one sighting, and still ends
        (``q-pace-cross``, lifted, seed 3: a second track for the person otherwise).
        False: position alone.
    shared_scans : int
        Two tracks that split one cluster between them (``share_m``) in this many of their
        sightings in a row, the two parts never seen apart
        (:func:`~nodlidar.tracking.segment.seen_apart`) and the two moving alike
        (``shared_dv_m_s``), follow one object: the younger ends. A box is one cluster;
        a second track born on it (its first track missed it for a scan: the nod's blind
        part, a prediction 0.6 m off) was confirmed, and the two took the box's cluster in
        turns (``design/scenes/track-edge-box-away.toml``, lifted, seed 5: 10 identity
        switches). Two people touching in the top view are seen apart, by a ray between
        them or a step in depth where one is partly behind the other; and two tracks that
        once took two different clusters in one scan (two objects, as the segmentation saw
        them) never end so: two people side by side, one cluster and unseen apart for four
        scans (``benchmarks/heldout/y-three.toml``, mirrors, seed 7). 0: off.
    shared_dv_m_s : float
        ... the two tracks' velocities (both estimated) differing by at most this [m/s].
    shared_fraction : float
        ... and the smaller part at least this fraction of the larger's points: the two
        halves of one object, not a track coasting behind an occluder whose prediction
        takes the edge of the person beside it (``benchmarks/heldout/y-three.toml``,
        mirrors, seed 2: 4-7 points of the neighbour's 50; at 0 its track ended and it
        got a second one).
    merge_seen_apart : bool
        Two clusters that the scan saw apart
        (:func:`~nodlidar.tracking.segment.seen_apart`: a ray passed between them, or the
        scan line jumps once in depth from one to the other) are two objects, however
        close: neither joins the other as a piece (``merge_m``). Centroid distance alone
        merged two people 0.42-0.45 m apart wherever their visible sides' centroids came
        within 0.38 m: walking away side by side, seen obliquely, or close to the sensor,
        one track took both for their first scans (docs/tracking.md "Two objects or
        one"). False: ``merge_m`` alone.
    merge_hidden_m : float
        A cluster left over within this [m] of a track's assigned cluster joins it when the
        scan saw nothing of the gap between the two: on the scan line from one to the
        other every beam ended in front of both
        (:func:`~nodlidar.tracking.segment.hidden_between`: a nearer object hides the gap).
        A box walking behind a person is cut by the person's shadow into two pieces
        0.4-0.45 m apart, beyond ``merge_m``; measured
        (``design/scenes/track-side-by-side-box.toml``, mirrors, seeds 0-7): identity
        switches 24 -> 0, and no other run of the harness changed. 0: off.
    merge_hidden_extent_m : float
        ... and only when the two together span no more than this [m] in the top view. Two
        people walking side by side behind a third are pieces on both sides of the third's
        shadow too, and span 0.78 m or more (centres 0.42 m apart or more, radius 0.18 m);
        measured (``design/scenes/track-two-behind-one.toml``, seeds 0-7), the merge
        without this bound took the hidden person's pieces into the other's track: their
        longest track's purity fell from 1.0 to 0.09-0.76 in 5 of 8 lifted seeds, and
        identity switches went 6 / 0 -> 6 / 2 (mirrors / lifted). The 0.5 m box spans
        0.5 m; a box or cart wider than 0.65 m behind a person keeps two tracks
        (``benchmarks/heldout/y-splitbox.toml``: 0.8 m).
    hold_seen_apart : bool
        A track does not take a cluster when its predicted position lies on another,
        nearer cluster of the scan that is not dynamic and that the scan saw apart from the
        first (its object is there, only not seen moving in this scan: a person walking
        away, or slowly, is dynamic in some scans only). Two people side by side, one of
        them dynamic in a scan: the other's young track, whose gate still spans both, took
        the one seen (docs/tracking.md "Two objects or one").
    follow_seen_through_m : float
        A moving track that took no cluster in a scan may take a cluster that is not
        dynamic when the scan sees through the track's own earlier voxels onto it: at
        least ``min_inconsistent_points`` and three quarters of the cluster's beams cross,
        within this distance [m] before their end points, voxels the track's points filled
        and this scan does not hit (:func:`~nodlidar.tracking.segment.seen_through`), and
        the cluster is object-sized and within the track's gates. This is "occupied, then
        seen through", the evidence of a person walking straight away from the sensor, to
        which "free, then occupied" is blind: the space the person's back moves into was
        behind it. Measured, seeds 0-7: a crossing where one person walks straight away,
        converged with mirrors 1/8 -> 8/8 seeds (8 identity switches -> 0); two people
        walking away side by side, lifted, 2/8 -> 8/8 (6 -> 0) (docs/tracking.md "Walking
        straight away"). 0: off.
    follow_inconsistent_fraction : float
        A track that took no cluster in a scan may take the cluster nearest its prediction
        that is not dynamic but has ``min_inconsistent_points`` inconsistent points and at
        least this fraction of its points inconsistent (a birth needs
        ``SegmentConfig.min_inconsistent_fraction``, 15 %): continuing an object needs less
        evidence than starting one. The cluster must be within the track's gates and
        object-sized (every point within 0.5 m of its centroid: without that, a ghost on a
        table's edge grew into the 1 m table), no static support may have judged it, and it
        may be at most 0.1 m wider (largest distance of a point from the centroid) than the
        track's last cluster: two people side by side seen as one cluster are not one of
        them. The nod shows an object at a new height each
        scan; where rays had not passed before, only a few of its points are inconsistent
        (a person crossing at 2 m, mirrors deployed: 76 points, dynamic once, then 8 of 73,
        3 of 70, 8 of 67 - its young track waited 21 scans for the next dynamic scan).
        1: off.
    smooth_scan_beams : int
        Each scan's points of a track move along their rays to a straight-line fit of range
        against beam step over this many beams either side
        (:func:`~nodlidar.tracking.motion.smooth_along_scan`) before the entropy sees them:
        less range noise, a narrower effective kernel. 0: off (default). Measured with 2
        (seeds 0-7, 1280 runs): converged mover-runs 901 -> 906 with mirrors and 882 -> 891
        lifted, but identity switches 24 / 14 -> 29 / 22 (the grid's 1 m/s back-and-forth
        turns) and more movers later with mirrors than lifted (14 -> 18)
        (docs/tracking.md, "Twelfth session").
    occluded_scans : int
        A track unseen for more than ``max_missed`` scans lives on by one scan for each scan
        since it was last seen in which its predicted place was hidden behind another
        track's object, up to this many: at least 3 beams, and more than pass through it,
        end on a cluster a track took in that scan, more than 0.15 m before a column of
        0.2 m radius at the track's predicted position, from the floor to the track's
        highest point (:func:`~nodlidar.tracking.segment.behind_or_through`). Hidden behind
        furniture or walls does not count: a start-up ghost coasting into them would live
        on. Measured, seeds 0-7: two people side by side along the line of sight
        (``design/scenes/track-side-by-side-tangential.toml``; the farther one unseen for
        35 scans), with mirrors, 8 identity switches -> 0; four people P3 with mirrors 7 ->
        0 (docs/tracking.md "Hidden behind another track's object"). 0: off.
    confirm_scans, max_missed, window_scans : int
    confirm_speed_m_s : float
        A track is confirmed (reported as an object) once seen in ``confirm_scans`` scans
        *and* once its speed has reached this [m/s] - surely, by one standard deviation,
        while its velocity is only two scans old (a person standing still read 0.05-0.11
        +- 0.09 m/s then; people walking at 0.13-0.3 m/s 0.15-0.3 +- 0.06-0.16). The
        default is the segmentation's static speed (``SegmentConfig.static_speed_m_s``,
        0.05 m/s): whatever moves slower is furniture to the segmentation, and to the
        tracker. A pole or a table's edge that rays pass beside is dynamic in the first nod
        sweep, before static support can judge it (nothing was hit there 2 s before), and a
        person standing still can be too; their tracks stay tentative while their speed
        reads ~0. Measured, seeds 0-7, every scene and the grid: false tracks mirrors /
        lifted 36 / 68 -> 27 / 53, the furnished room's standing person confirmed in no run
        (before: 16 of 16), no other mover's identity, estimates or convergence changed
        (the grid's 0.05 m/s movers included); 17 held-out-style scenes 29 / 33 ->
        16 / 28. 0: off.
    confirm_sure_scans : int
        How many scans old a track's velocity must be before its speed alone confirms it;
        younger, its speed less one standard deviation must reach ``confirm_speed_m_s``.
        3 (default): surely only for the two-scan velocity. Measured with 4 (seeds 0-7,
        every scene of the harness): false tracks 29 -> 24, all on the pole of the
        cart-and-table scene (``benchmarks/heldout/v-cartable.toml``: dynamic in the first
        nod sweep, its speed 0.080, 0.067, 0.044, 0.032 m/s over scans 2-5), and no mover's
        convergence, identity or estimate changed; but a mover at 0.05 m/s is first
        confirmed up to 19 scans later (at 89.4 deg, seeds 0-3 with and without mirrors:
        scans 8 26 29 12 7 26 8 26 -> 27 27 29 26 8 27 26 27). An option for cluttered
        rooms, not the default.
    confirm_sigmas : float
        At any age, a track's speed must also be this many standard deviations (of the
        filtered velocity, along it) from zero to confirm it: a speed as large as its own
        uncertainty is no evidence of motion. A thin pole or lamp, dynamic in the first nod
        sweep, read 0.054-0.093 +- 0.063-0.125 m/s at its third scan (speed / sd 0.6-1.05)
        and was confirmed by its speed alone; a 0.05 m/s mover reads 1.3-2.5 sd from zero
        then, more as its scans add up. Measured on the first 12 scans of 44 tracks of
        static things and 80 of movers (seeds 0-3: the cart-and-table, pole and furnished
        scenes, the grid's 0.05 m/s movers, the slow box): of the 10 static ones the speed
        alone confirmed, 1.5 leaves 3; of the 78 movers it confirmed, 63 are confirmed at
        the same sighting, 14 one to seven sightings later and 1 not in those 12, every one
        of the 15 a 0.05 m/s mover (at the static speed itself). Over the harness (seeds
        0-7, 1568 runs) false tracks 28 -> 18, and one mover-run lost: a 0.05 m/s mover
        (the grid's 135 deg, lifted, seed 5) that reads 0.042-0.046 m/s once its first
        sweep is past, confirmed before on a third-scan 0.104 m/s; no other mover-run's
        convergence got later (docs/tracking.md, "Fourteenth session"). 0: off.
    confirm_overlap : float
        A track is confirmed only on a velocity that lays its sightings on one another: moved
        back along it to the latest sighting's time, of the latest sighting and the earlier
        ones (since the motion started) the better covered must have at least this fraction
        of its points within ``_OVERLAP_M`` (0.1 m) of the other, in the top view. The same
        object seen twice, whole or growing into the view, is covered; two parts of a piece
        of furniture that the nod met in turn (a table's top, then its front edge, from a
        driving robot: 0.99-1.27 m/s) are not. Measured at the confirmation of every track
        over the harness's scenes (seeds 0 and 1, 809 tracks): movers 0.66-1.0 (8 of 802 below
        1.0), the static world's 0.30-0.39 in three of seven, 0.66-1.0 in the rest.
        docs/tracking.md "Twenty-first session". 0: off.
    hold_sliding_lines : bool
        Where a track's object is a thin straight line in the top view (its last 3
        clusters, moved back along its velocity: a face seen alone) whose extent those scans
        have not shown (two of them with a slice of the same length, within 5 cm, whose
        two ends are the object's outline: :func:`~nodlidar.tracking.segment.silhouette_ends`),
        only its speed across the line confirms it, less the part of its speed along the
        line that the line's uncertain direction (minor / major spread, in radians) turns
        across. Along the line only the slices' ends place it, and where the nodding scan
        line leaves a face over its top or at its foot, that end moves with the nod: the
        front face of a table cut by a mirror window's edge at start-up read 2.2-2.7 m/s
        along itself and was confirmed at its second scan (``track-room-furniture`` with
        mirrors: a false track in every seed). Measured, seeds 0-7, every scene of the
        harness (1440 runs): false tracks 26 / 18 -> 6 / 16 (mirrors / lifted), switches 31 /
        38 -> 31 / 36; no mover's convergence changed. Its price: a box face-on at the
        mirrors' view edge, moving along its face and seen for 3-5 scans, is left tentative
        in 7 of 8 seeds (confirmed before, its speed off by 0.29-2.0 m/s in 4 of them, within
        0.05 m/s in 3; ``track-edge-box-away``; docs/tracking.md "Thirteenth session").
        False: the speed along the line counts.
    entropy, sigma_m, voxel_m, max_points, voxel_max_points, warm_search_m_s, warm_voxel_grid
        The entropy refinement (:func:`refine_motion`); ``max_points`` (Rényi) and
        ``voxel_max_points`` cap the points one refinement uses (bounded work per scan).
    keep_points : bool
        Keep every scan's points per track (an analysis of the whole track, e.g. the
        mirror study's estimate after each scan count); by default only the last
        ``window_scans`` scans' points are kept, so a long-lived track's memory stays
        bounded (the per-scan centroids and times are kept).
    position_sigma_m : float
        Measurement noise of the centroid [m] (the visible part of an object changes with
        the nod and the mirror window: a 0.4 m box's visible centroid moves by ~0.2 m).
    velocity_sigma_m_s : float
        Least measurement noise of the entropy velocity [m/s] (the refinement's own curvature
        covariance is unscaled; this floors it).
    accel_sigma_m_s2 : float
        Constant-velocity process noise: white acceleration spectral density, as a sigma
        [m/s^2 per sqrt(Hz)] (people and robots at walking pace change velocity slowly).
    velocity_fusion : {"kalman", "window", "first"}
        How the entropy velocity enters the filter. ``"kalman"`` (the default before issue
        13's overlap fix; kept for comparison): an independent
        measurement every scan, noise = the refinement's curvature covariance + the floor -
        it smooths the estimate's scan-to-scan jitter, but successive windows share their
        scans, so it counts each scan many times over, and the zero-velocity birth prior
        and the first scans' estimates linger. ``"window"``: each scan's estimate over the
        track's window supersedes the previous one (the prior's velocity is forgotten;
        noise = the floor): no lag, but the jitter passes through (slow movers).
        ``"first"``: ``"kalman"`` with the birth prior forgotten at the first estimate.
        ``"overlap"`` (default): the lag's causes removed at once (:meth:`Tracker._velocity_noise`):
        the birth prior forgotten at the first estimate, the Rényi curvature covariance
        calibrated (divided by the points in the sum: the cost is a mean over them), and
        inflated by the scans in the window (a window of ``n`` scans shares ``n - 1`` with
        the previous one: each estimate carries ~1/n new information, so the filter counts
        every scan once). docs/tracking.md has the measurements of each.
    renyi_subsample : {"pairs", "points"}
        Beyond ``max_points`` points in the window, the Rényi sum keeps ``max_points`` points
        (``"points"``) or every point with as many random pairs as ``max_points`` points
        have (``"pairs"``, :class:`~nodlidar.tracking.motion.RenyiCost`: the same work,
        and the density mirrors add is not thrown away; default).
    renyi_pairs : {"all", "window", "adaptive"}
        Which pairs the Rényi sum takes: all, or only pairs of points seen through the
        same mirror window (``"window"``; the window is ``scan.mirror``): the terms between
        windows bias the first estimates of a mover along the line of sight
        (docs/tracking.md, "Along the line of sight"), but over the scenes ``"window"`` is
        not better as a whole. ``"adaptive"`` (default): pairs within a window while the
        track's window holds fewer than ``renyi_all_pairs_scans`` scans, all pairs from
        then on (the terms between windows bias a window of 2-4 scans and help a longer
        one); over seeds 0-7 of the scene files and the speed x heading grid no mover gets
        later than lifted that was not, and 0.3 m/s along the line of sight stops being
        later (docs/tracking.md, "Adaptive pairs"). Lifted scans have one window: the
        three are the same there.
    renyi_all_pairs_scans : int
        ``"adaptive"``: the scans in the track's window from which all pairs are taken (6:
        the diagnosis measured the bias between windows at 2-4 scans, -15 to -1 deg, and
        the terms between windows helping at 6 scans, -0.13 deg with them, -0.46 without).
    box_pairs_speed_m_s : float
        A track the round model found no circle in (its last cut window's fit failed the
        radius, RMS or serial gate, or a window of 200 points or more gave no circle at
        all: a box, a cart; never with ``round_model="off"``) moving at this speed [m/s] or
        more takes only pairs within a mirror window, at every window length: each window
        sees its own faces of a box, and between windows the kernel aligns the faces'
        densities, not the surfaces (a 0.8 m box at 0.4 m/s read 2 % slow for 20 scans
        with all pairs). A slow box keeps the terms between windows, which tie the views together
        (a 0.6 m box at 0.05 m/s did not converge without them). Default 0.2 (chosen
        between those two before it was measured); 0: off. Measured over the harness
        (seeds 0-7, 2096 runs; lifted unchanged, it has one window): with mirrors 54
        mover-runs sooner, 42 later, converged 1503 -> 1508; ``track-box-fast`` 52.5 ->
        38 (lifted 50.5), ``x-box08`` 49 -> 39, ``r-cart-corner`` converges (67.5);
        ``u-far-fast`` 40 -> 44 (one seed of eight, 34 -> 43); identities, switches and
        false tracks unchanged (docs/tracking.md, "Twenty-sixth session").
    reacquire_speed_m_s : float
        A track with no velocity yet (seen in one scan only) may take a cluster up to
        ``max(gate_m, reacquire_speed_m_s * dt)`` from where it was seen, ``dt`` the time
        since then [s]; 0: ``gate_m`` always. Its prediction is where it was seen (the birth
        velocity is zero), so after a gap the fixed gate loses it even though the object is
        still there: with mirrors and per-window segmentation, side-by-side seed 1 finds the
        right person at scan 3, 3.25 m out, then not again until scan 26 (coming towards
        the sensor in its own shadow, then the nod's blind part): 0.75 m away, beyond the
        0.6 m gate, so a new track took the person (an identity switch). The chi-square
        gate still applies (the birth velocity's 0.5 m/s sigma grows the predicted
        position's covariance with ``dt``).
    reacquire_births_m_s : float
        A new object (a dynamic cluster no track took) is, instead of a new track, the
        continuation of a *lone* track - one without a velocity yet, not seen in this scan -
        that could have got there at this speed [m/s], when nothing else could be it: no
        other cluster of the scan (dynamic or not, taken or not) is nearer to where the
        track was, and no other lone track claims the cluster. A person seen in one scan
        before the nod's blind part (mirrors, 3.5 m out: every ray of the lower nod hits
        the floor before them for 10 scans) is 1.2 m on at 0.6 m/s when seen again, beyond
        any gate of a track without a velocity. Re-acquisition without the nearest-cluster
        guard (measured, docs/tracking.md "Re-acquisition of lone tracks") gave a lone
        track to another person while its own was not dynamic, or was in a cluster a ghost
        had taken, and start-up ghosts on furniture (the furniture is always nearest to a
        ghost's place) reached movers. 0: off.
    reacquire_forget_scans : int
        A track re-acquired so (``reacquire_births_m_s``) drops its sighting before the gap
        from its motion window when it has this many since, if their own entropy
        estimate differs from its velocity by more than ``maneuver_m_s / 2``: that one
        sighting only started the velocity, and it may have been another object moving
        with this one (``benchmarks/heldout/s-push.toml``, mirrors, seed 3: a person seen
        once, then the trolley they pushed ahead of them re-acquired the track after the
        nod's blind part; with the person's points in its window the trolley read 0.085
        m/s fast to the end of the run, 39 scans later). Unconditional, it cost correct
        re-acquisitions their long baseline (the 0.8 m box converged 11 scans later with
        mirrors, median of seeds 0-7). 0: never.
    reacquire_gone_only : bool
        A track seen in one scan only is not re-acquired by a cluster it could have reached
        only by leaving its place earlier than a scan found something still there: the
        latest scan whose beams met a person-sized column at that place (0.2 m, floor to
        its highest point) found most of them ending inside it (:meth:`Tracker._look_at_place`),
        at a time when, at the speed the continuation implies, the object would have been
        clear of it: more than 0.55 m away (the column, its margin, and the object's own
        radius, taken as the column's). A start-up ghost on furniture stays where the
        furniture is; a person seen once and walking on is near their place only for as
        long as their speed allows. Measured (``track-pace-room``, lifted, seed
        4): a ghost seen once on the table at scan 35 took the lamp 2.2 m away at scan 57
        (dynamic as a person passed behind it) and was confirmed at the 1 m/s of the jump;
        with this, no false track. Over the harness (seeds 0-7, 1568 runs) false tracks
        7 / 11 -> 6 / 10 and switches 34 -> 33 (mirrors / lifted), no mover-run later
        (docs/tracking.md, "Fourteenth session"). False: any continuation within reach.
    reacquire_unique_m : float
        A track seen once (no velocity yet) and unseen for more than ``turn_scans`` scans
        is not given the nearest new object when another moving object that appeared since
        it was seen (a new cluster, or one a track born since took) is at most this much
        [m] farther from its place: one sighting gives no velocity to tell them apart, and
        the nearer is not surely it. Each new object within that band starts a track
        pending on it, and the one whose own path, traced back at its velocity, passes
        within ``stitch_turned_m`` of the sighting at its time continues it
        (:meth:`Tracker._stitch`, as for a moving track lost in a turn); none does when a
        track born since passes nearer, and then the track seen once ends unconfirmed: a
        report a scan or two later instead of a wrong identity. Measured
        (``benchmarks/heldout/y-three.toml``, mirrors, seed 0): the person seen once at
        scan 1 behind the front one was 0.52 m on when seen again at scan 27, and the
        person beside them had walked to 0.24 m from the sighting; the track took the
        nearer one, an identity switch. 0: off (the nearest, as before).
    reacquire_moving : bool
        Opt-in: the same for a moving track unseen for more than ``turn_scans`` scans,
        within its own speed x the time since it was seen + ``gate_m`` of where it was
        seen; its motion starts afresh (it turned unseen). Measured, seeds 0-7 (992 runs,
        docs/tracking.md "Moving tracks re-acquired by new objects: measured, opt-in"):
        the grid's back-and-forth movers, turning in the nod's blind part, lose their one
        switch per seed (98 runs); but a person's track took the robot in the robot
        crossing (4 seeds, mirrors), and the furnished rooms' walkers got switches (7 runs).
        ``stitch_turned_m`` is the default way to the same end.
    stitch_turned_m : float
        A new object that only a lost moving track (unseen for more than ``turn_scans``
        scans) could be, by the same guards as ``reacquire_moving``, starts a track of its
        own, not confirmed for its first ``_STITCH_SCANS`` (4) sightings; at each with a
        velocity, it continues the lost track when their motions meet: the lost track's
        path from where it was last seen and the new track's path traced back come within
        this distance [m] of each other at one moment between the sightings (where and when
        it turned), at speeds within 30 % (or 0.1 m/s) plus twice the lost track's speed
        uncertainty. The lost track then takes the new one's scans, its motion starting
        afresh. A static ghost, or another mover that appears where the lost one might have
        turned, does not move from that place and moment. Measured, seeds 0-7, every scene
        and the grid (928 mover-runs): identity switches mirrors / lifted 57 / 52 -> 4 / 5
        (the grid's back-and-forth movers, three people, the furnished room's walker), no
        other mover-run's identity or purity changed; on 17 held-out-style scenes
        (crossings, side by side, a robot crossing a person's path, a cart pushed past a
        table, two people pacing) 25 / 15 -> 3 / 8
        (docs/tracking.md "A mover that turned unseen"). 0: off.
    stitch_stopped : bool
        ``stitch_turned_m`` also for an object that stopped or slowed on its way unseen
        (the new track slower than the lost one, at any speed below it) and for one that
        stood still and walked off unseen (the lost track slower than
        ``confirm_speed_m_s``: the new one at any speed, and its reach
        ``reacquire_births_m_s`` x the time unseen, as for a track seen once); the paths
        must still meet. Measured on ``benchmarks/heldout/r-stopgo.toml`` (a person who
        stops for 3 s while the nod looks away), seeds 0-7: an identity switch in every
        run before, none after. False: the speeds within the tolerance above.
    ambiguous_chi2 : float
        A moving track seen again after the nod's blind part (more than ``turn_scans``
        scans unseen) whose motion gates two clusters whose costs differ by less than this
        (chi-square units; two objects: farther apart than ``merge_m``, free space seen
        between them - or a nearer object hiding the gap, the two together wider than
        ``merge_hidden_extent_m`` - and neither predicted better by another track) takes
        neither: the data
        of that scan cannot tell them apart. Each becomes a new track pending on it, and
        the one whose motion meets the lost track's path nearest continues it
        (``stitch_turned_m``), once each has a motion. Measured: two people side by side
        0.42 m apart, one seen twice before the blind part with a velocity 15 deg off
        (sd 0.11 m/s); 1.8 s on the two cost 4.16 and 4.35, and the lower took the track
        (an identity switch; ``design/scenes/track-side-by-side-blind.toml``, mirrors,
        seed 5). Over every scene and the held-out-style ones (1824 runs) it changed that
        run only. The hidden gap since 2026-12-07: L and R one behind the other behind a
        front person who hid the gap between them cost 7.36 and 7.50, and the track took
        R (``design/scenes/track-two-behind-one.toml``, mirrors, seed 3). 0: off.
    turn_reach_m : float
        A track with a velocity, seen in one of the last ``turn_scans`` scans, may take a
        cluster that fails its constant-velocity gates but lies within ``turn_reach_m`` +
        its speed x the time since it was last seen of its last centroid: the object
        turned or stopped (a person pacing, a robot reversing). The pair costs more than
        any gated one (``gate_chi2`` + (distance / reach)^2), so the assignment prefers
        the motion model; when it wins, the track's motion starts afresh from that
        cluster (window emptied, velocity prior of a birth) and keeps its id. Measured
        before: a 1.0 m/s mover reversing on its 3 m leg overshot the gate within two
        scans and got a new track at every turn. 0 turns it off.
    turn_scans : int
        See ``turn_reach_m``.
    maneuver_m_s, maneuver_scans : float, int
        A track whose object stops or starts within its gates (a person who waits, then
        walks on) keeps its id and its confirmation but restarts its motion. Each update
        fits a line to the centroids of its last ``maneuver_scans`` sightings (this one
        included, all since its motion last started; of the slices no edge cut - a
        view's or window's edge, an occluder - in all but one); where against that
        velocity its filtered speed more than halved or doubled, by more than
        ``maneuver_m_s`` [m/s], the entropy estimate of its latest ``(maneuver_scans - 1)
        // 2 + 1`` sightings alone must agree (its speed changed so too, and it lies
        within ``maneuver_m_s / 2`` of the centroids' velocity, or for a start from
        standing or a turn at one speed beyond it along the same change, up to twice as
        far: the line fit lags a change it spans in part); then the window restarts
        with those sightings and the velocity prior with a birth's. Without it the window
        (up to ``window_scans``) mixed the two motions: measured on
        ``benchmarks/heldout/r-wait-pass.toml``, lifted, seed 0, a person who stopped
        read 0.49 -> 0.36 m/s over the next 12 scans while its track ran 0.34 m ahead of
        them, and after walking on read 0.005 -> 0.17 m/s over 12 scans. The threshold:
        on 88 runs of 22 scenes (seeds 0-1) the centroids' velocity differed from a
        filtered velocity that was right (within 0.1 m/s) by more than 0.3 m/s at 6
        sightings of 4 runs, and by more than that at 116 of the 178 sightings where the
        filter was 0.2 m/s or more off, in 25 of the 26 runs with such sightings. Any
        velocity change on all centroids (the first form) restarted tracks on partial
        views (a person half hidden, a box leaving the view, a driving robot's angle):
        70 fewer converged mover-runs with mirrors over the harness (docs/tracking.md
        "Fifteenth session"). 0: off.
    maneuver_turn_deg : float
        A turn within the gates restarts the motion too: against the centroids' velocity
        the filtered one changed by more than ``maneuver_m_s`` and its heading by more
        than this [deg], the speed kept within a factor of two (a speed that fell to a
        quarter while the heading swung is neither: a box leaving the view read so), and
        the latest sightings' own estimate agrees, as for a stop. Two people who meet
        0.5 m apart and turn together to walk on (``design/scenes/track-meet.toml``)
        stayed within both tracks' gates, each filter carried its track straight on, and
        the two tracks crossed and swapped people 5 scans after the turn. A slow walker's
        right angle (0.13 m/s: 0.18 m/s of change) is left to the turn gate
        (``turn_reach_m``). 0: stops and starts only.
    maneuver_late_lag : float
        A turn at one speed (or a start) whose latest sightings' estimate lies beyond the
        centroids' velocity by more than twice the line's change but at most this many
        times: the line lags that much when the change came within the latest sightings'
        span, so the oldest of them is (partly) from before it, and the motion restarts
        with the ones after it only (one sighting fewer) - if the next sighting confirms
        the change, by this test or the two-fold one again, or as a turn beyond the gates
        (``turn_reach_m``). A reversal that the two-fold bound refused (``grid 0.6 x
        89.4``, mirrors, seed 0: the latest three sightings read 0.572 m/s at -90.7 deg
        against the track's 0.594 at 89.3, 2.25 times the line's change) was left to the
        turn gate, restarted from one scan, read 0.72 m/s at 124 deg from two and lost
        its track in the nod's blind part (converged 73; lifted 67); restarted here it
        converged at 66. The same bound with the oldest sighting kept started a
        reversing box slow (0.51-0.53 m/s for 0.59) and converged later or never
        (docs/tracking.md "Twenty-eighth session"); without the next sighting's
        confirmation a box whose face changed with the nod (``track-edge-box``, mirrors,
        seed 4: its line read 0.03 m/s, its latest sightings a reversal) restarted and
        converged at 68 instead of 27. A line of the sightings with two cut (all but two
        uncut, where the maneuver test asks all but one) may propose such a restart, by
        either bound, but never makes one: the mirrors' windows cut a 0.6 m/s mover at
        135 deg in two of the six sightings around its reversal (``grid 0.6 x 135``,
        mirrors, seed 0), the turn gate then restarted from one scan and the motion
        converged after the nod's blind part (66); with the proposal the gate's restart
        takes the two sightings after the turn and it converged at 56 (lifted 66).
        Letting that line restart by itself cost 8 identity switches and a cart's
        convergence over the harness. 0: off.
    maneuver_stop_lag : bool
        A stop, too, may lie beyond the centroids' velocity by up to the lag bounds above
        (the latest sightings' estimate under 30 % of the filtered speed), as a start from
        standing and a turn at one speed may: the line lags a stop as it lags a start. A
        person who walked away at 1.1 m/s and stopped 4.8 m out (lifted, seed 4: the
        latest three sightings read 0.09 m/s, the line 0.53, the track 1.10) was refused,
        left to the turn gate a scan later, and restarted from one scan; a two-scan window
        of 12-point sightings read 0.49 m/s, and the track still read 0.16 m/s eight
        scans into the stop. Restarted here with its three sightings it read 0.04.
        (``design/scenes/track-stop-far.toml``; over the harness, with the two options
        below, docs/tracking.md "Thirtieth session".)
    maneuver_before : bool
        The maneuver test also compares the line with the filtered velocity *before* the
        line's first sighting, where that one was settled (the motion's window then held
        ``maneuver_scans`` sightings or more, and the line lies wholly after the
        motion's start by as many): the filter has taken in part of the change since,
        through windows that mix the two motions, so a start or a stop slower than about
        0.5 m/s never lay ``maneuver_m_s`` from the current velocity. A person who stood
        3 s, then walked at 0.6 m/s (``design/scenes/track-start-still.toml``, mirrors,
        seed 1) read a speed that ramped over 13 scans (0.10 -> 0.57 m/s) and converged
        at 72; restarted at the 8th sighting of the walk it reads 0.59-0.60 from the
        next and converged at 40.
    maneuver_after_gap : bool
        The line takes only the sightings since the track was last unseen for longer than
        the line spans (more than ``maneuver_scans - 1`` times the sightings' median
        spacing: the nod's blind part), and waits until they are
        ``(maneuver_scans - 1) // 2 + 2``: across the gap it mixes the motion before
        with the one after. Two people who stood 3 s and walked off while the nod looked
        away (``design/scenes/track-meet-stop.toml``) read 0.16-0.26 m/s over five
        sightings for 0.5, their tracks fell behind and lost them: an identity switch
        in 6 of 16 runs, none with it.
    follow_supported_m_s : float
        A track moving at least this fast (filtered speed [m/s], and at least three
        standard deviations of it from zero: a track that coasted unseen is not sure to
        move) may take, within its constant-velocity gates, a cluster that is dynamic
        only without static support
        (:attr:`~nodlidar.tracking.segment.Segmented.supported`); such a cluster never
        starts a track nor joins one as a piece. Static support (a voxel also hit 2 s
        earlier) keeps furniture out of the dynamic set, but a mover back on its own path
        within the map's window - a person pacing, a robot reversing - is there too: before,
        a 1.0 m/s mover on a 3 m back-and-forth leg lost its track a few scans after each
        turn. Only a cluster whose support is the tracks' own earlier points qualifies: at
        least half of its points lie in voxels that some track took ``static_age_s`` or
        more before, in a dynamic cluster, once the map was ``static_age_s`` old. Where a
        person passes a doorway the cluster is the door frame with the person (measured
        in the furnished room, seed 6: 69 wall points, 25 the walker's), supported by the
        frame's own hits long before; taking it dragged the track onto the wall. A
        start-up ghost's table points, or a supported cluster taken, do not count: a ghost
        would make the table its own path (measured in the three furnished rooms, seed 0,
        mostly static clusters taken per run: 0-21 before, 0-7 after). The default is
        twice the segmentation's ``static_speed_m_s``: a mover that fast cannot itself
        have been in its voxel 2 s ago. 0 turns it off.
    window_cut_speed_m_s, window_cut_drop_m_s : float
        A slice of an object cut off by its window's edge
        (:func:`~nodlidar.tracking.segment.window_cut`) ends at a beam fixed in the sensor,
        which pulls the entropy's motion across that beam towards zero; the narrow mirror
        windows cut objects often. In the Rényi sum a cut slice's points weigh
        ``min(1, window_cut_speed_m_s / v_across)`` (times their incidence weight),
        ``v_across`` the track's speed across the slice's beams [m/s], relative to the
        sensor (``ScanPoints.sensor_velocity_m_s``: the beam moves with a driving robot;
        measured, a person overtaking a robot at 0.6 vs 0.3 m/s into the mirrors' view,
        ``design/scenes/track-overtaking-robot.toml``, converged at scan 25 -> 16.5 with
        mirrors, median of seeds 0-7, with the relative speed): along the beam the
        cut pulls nothing, and the pull grows with the speed across it (measured: ~5 % of
        it; a person entering three mirror windows at 0.42 m/s across them read 0.016 m/s
        slow and 2 deg off, noise-free). Where ``v_across >= window_cut_drop_m_s`` the
        slice is left out (both entropies), once the slices left are most of the window's
        points and a cluster's worth (``SegmentConfig.min_cluster_points``) in two of its
        scans: a person entering the view is cut in every slice, and its 3-4 points per
        scan left read 45 deg off (``benchmarks/heldout/q-near.toml``, mirrors, seed 0,
        scan 8; converged at scan 17 -> 16, median of seeds 0-7). Leaving every cut
        slice out instead starved slow movers (0.05 m/s at 45 deg: convergence scan
        20 -> 35 with mirrors, lifted 20). ``inf``: cut slices
        weigh as any other / are never left out. docs/tracking.md "Slices cut by a
        window's edge". 0.4 m/s since the occluder cuts below (0.5 before: a walker
        0.42 m/s across the windows kept its biased cut slices).
    window_cut_reach_m, window_cut_occluders : float, bool
        Where a slice really ends (:func:`~nodlidar.tracking.segment.window_cut`): each
        end is followed through neighbouring beams of its window whose points lie within
        ``window_cut_reach_m`` [m] of each other (the object's own points that the
        segmentation left out of the cluster), and with ``window_cut_occluders`` a
        nearer return there is a cut too (an occluder's edge is not the object's
        outline). Both feed the weights and the dropping above. Measured, seeds 0-7,
        median convergence scan mirrors / lifted: a 0.95 m/s walker coming out from
        behind a slow one 23 / 32 -> 13 / 22; the four-person room's P1 31.5 / 13 ->
        27 / 14 (docs/tracking.md "Slices cut by an occluder"). 0 and False: the
        cluster's own ends, window edges only.
    window_cut_mask : {"edges", "all", "off"}
        Rényi only: a pair of points of two scans enters the sum only where each point,
        moved by the track's velocity to the other's time, lies on the seen side of the
        lines where the other's slice was cut (:func:`~nodlidar.tracking.segment.cut_edges`,
        :class:`~nodlidar.tracking.motion.RenyiCost` ``edges``): a part of the object one
        of the two scans could not see is not compared. ``"edges"`` (default): the lines of
        windows' and the view's edges, for slices the track crosses at
        ``window_cut_speed_m_s`` or more; ``"all"``: occluders' edges too; ``"off"``: every
        pair. With mirrors deployed the view ends at +-40 deg, and an object entering it is
        seen up to that line for many scans. Measured, seeds 0-7, median convergence scan
        with mirrors (lifted unchanged): a person 0.8 m to the side walking away at
        0.3 m/s 38 -> 26.5 (lifted 4: it starts outside the view), the same overtaking a
        robot that drives at 0.3 m/s 35 -> 25 (16.5 with the speed across relative to the
        robot, ``window_cut_speed_m_s``), side by side on the diagonal (left) 26 ->
        14.5 (lifted 10), near the sensor (left) 25 -> 13, a fast crossing (A) 12 -> 8
        (lifted 6). ``"all"`` lost slow movers half hidden by a neighbour (side by side at
        0.13 m/s, right: 3 of 8 seeds converged). docs/tracking.md "Comparing only what
        both scans could see".
    window_cut_floor : bool
        The floor cuts slices too (:func:`~nodlidar.tracking.segment.cut_edges`
        ``floor_z_m``, the segmentation's ``ground_z_m + ground_clearance_m``): where the
        nodding scan line meets the floor's height at an object's foot, the beams beyond
        reach the floor first and the slice ends at the line where the scan crosses that
        height - fixed in the sensor for that scan, like a window's edge, and weighed,
        left out and masked as one (the speed across it: across that line). Measured,
        seeds 0-3, with mirrors: a person 0.8 m to the side walking away into the view
        converged at scan 25-28 without, 15-17 with (the window's last scans met the floor
        at its foot and read 7 % slow, noise-free). docs/tracking.md "Slices cut by the
        floor".
    max_speed_m_s : float
        A refinement faster than this [m/s] is no motion but the minimiser run off where
        the cost is flat (no pair of points near the start spans two scans): the warm
        start is dropped for a cold one from the centroids, and if that runs off too the
        scan gives no velocity measurement. Measured: 169 m/s, warm-started from a wrong
        velocity after a mover turned in the nod's blind part. 5 m/s is above a running
        person's speed.
    debias_sigma_m : float
        Opt-in: a second Rényi refinement per scan with this kernel width [m], warm from
        the first, and the speed extrapolated to a zero-width kernel (:func:`_debiased`).
        The kernel-smoothed sum aligns a passing object's visible masses rather than its
        shape, and the visible arc turns with the bearing: the speed reads slow, by an
        amount about linear in the kernel's width, and range noise widens the kernel
        (analytic fan, 1 m/s 2.5 m ahead, 2.5 cm noise, 16 scans:
        -0.0064 m/s with 2 cm, -0.0010 extrapolated from 3 cm, mean of 30 draws;
        ``tests/test_tracking_debias.py``).
        Over the harness (seeds 0-7, 1824 runs) with 0.03 and the two bounds below, the
        final speed is closer (within 0.01 m/s in 95.6 / 95.2 % of mover-runs against
        94.9 / 94.2, mirrors / lifted; 1300 / 1298 converged against 1290 / 1285), but the
        extrapolation's spread makes more mover-runs converge later than earlier (with
        mirrors 128 later, 79 earlier; lifted 163 and 122), identity switches go 39 / 33 ->
        42 / 39, and more movers converge later with mirrors than lifted (18 -> 21): not
        the default (docs/tracking.md, "Nineteenth session"). 0: off (default).
    debias_min_speed_m_s, debias_max_cut_fraction : float
        ... only for tracks at this speed [m/s] or more (the bias grows with the speed;
        below it the extrapolation adds spread only) and windows with at most this fraction
        of their points in cut slices (a cut's bias is not the kernel's, and the
        extrapolation doubled it: with no bound, a person entering the mirrors' view
        converged at scan 27 instead of 15, median of seeds 0-7).
    round_model : {"off", "cut", "always"}
        A round object's velocity from its outline
        (:func:`~nodlidar.tracking.round_motion.fit_moving_circle`): a circle of one radius
        moving at one velocity, a centre per mirror window, fitted to the window's
        ground-plane points. Where the fit holds (below), its velocity enters the scan's
        measurement, fused with the entropy refinement's (``round_fuse``; the refinement's
        covariance is kept: the filter's noise model stays the one calibrated for the
        window). ``"cut"`` (default): only for
        windows with a slice cut by a window's or the view's edge, an occluder or the floor
        - there the entropy reads the speed across the cut weakly, and a vertical
        cylinder's centre moves with it whatever part of it is seen; ``"always"``: every
        window (measured over the harness: lifted gains more than mirrors, converged
        1503 / 1482 -> 1500 / 1492, and more movers converge later with mirrors, 21 -> 26;
        docs/tracking.md, "Twenty-sixth session"); ``"off"``. Measured, mirrors, median of
        seeds 0-7: the paper's cylinder at 0.05 m/s, heading 0, 15 -> 8 (lifted 15.5); a
        fast crossing (``x-fast``) and a close pass (``s-close-pass``) converge (they did not);
        a person entering the view on the diagonal 12 -> 11.
    round_radius_m : (float, float)
        The fitted radius must lie in this range [m] (a person, a post; a box's flat face
        fits a circle metres wide).
    round_max_rms : float
        ... and the residuals' RMS, each divided by its beam's range noise (the lidar's
        ``range_sigma``; 1 cm without it), at most this (a cylinder: about 1; a box's
        corner: several).
    round_max_serial : float
        ... and the correlation of neighbouring points' residuals along a slice
        (:attr:`~nodlidar.tracking.round_motion.RoundFit.serial`) at most this: a circle
        that leaves only noise leaves it uncorrelated (measured on the simulator's people
        and posts: -0.13 to 0.04), one that leaves a shape does not (a 0.5 m box's corner
        beside a person: 0.18-0.46, at a normalised RMS of 0.9-1.2 that alone passes).
    round_max_sd_m_s : float
        ... and the fit's velocity sd (larger axis) at most this [m/s]: the first scans of
        a cut window determine a circle poorly.
    round_fuse : bool
        Where the fit holds, the measurement is the circle's and the entropy's velocity
        fused at their own covariances (the refinement's per window, as
        :meth:`Tracker._velocity_noise` calibrates it: Rényi's inverse Hessian over the
        points in the sum, the voxel grid's spread), not the circle's alone: across a cut
        the entropy is flat and the circle decides, and where the entropy reads the motion
        well it keeps its weight. Without a usable entropy covariance, the circle's alone.
        Measured over the harness (seeds 0-7, 2096 runs; docs/tracking.md "Twenty-fifth
        session"): the circle alone made far people converge later with mirrors (``q-far``
        45 -> 47.5, ``u-far-fast`` 39.5 -> 47.5); fused, no mover's median with mirrors is 2
        scans or more later, and 419 mover-runs converge sooner, 202 later (converged
        1486 / 1473 -> 1503 / 1482, mirrors / lifted).
    round_filter_cov : bool
        Where the fit is fused, the filter takes the fused velocity at the fused
        covariance (the circle's information added to the entropy's), not at the entropy's
        alone: the measurement then says what it holds, so a window the circle pins down
        outweighs the filter's memory of earlier, cut windows. Default on. Measured over
        the harness (seeds 0-7, 2096 runs; docs/tracking.md "Twenty-seventh session"):
        mover-runs sooner / later 171 / 40 with mirrors, 113 / 23 lifted; converged
        1508 / 1482 -> 1511 / 1481; identities, switches and false tracks unchanged.
    round_warm : bool
        Start each scan's fit from the last scan's where that held (its radius, velocity
        and centres moved on at its velocity): the same minimum in fewer Gauss-Newton
        steps (the paper's scene, 200 scans with mirrors: 3.2 per fit instead of 4.6).
        Default on; off: every fit starts from the algebraic circle at the entropy's
        velocity.
    incidence_weights : bool
        Rényi only: weight each point by ``1 / cos(incidence)`` (:func:`incidence_weights`)
        so the entropy counts surface, not beam density (default; docs/tracking.md "Fast
        walkers"). Measured, seeds 0-7: a 0.9 m/s walker passing 2.5 m ahead converged
        in 1/8 (mirrors) and 4/8 (lifted) seeds before, reading 0.010-0.016 m/s slow; 7/8
        and 8/8 with the weights. False: every point counts one.
    renyi_method : {"newton", "nelder-mead"}
        Rényi minimiser (:func:`refine_motion`); Newton's method on the closed-form
        derivatives takes a few passes over the pairs instead of ~50 (same minimum within
        the Nelder-Mead tolerance).
    newton_recentre : bool
        Newton only: where Newton's minimum lies beyond the pairs gathered around the warm
        start (``warm_search_m_s``; a young track whose velocity is still settling), gather
        them again around it and go on with Newton (:func:`refine_motion`), instead of
        Nelder-Mead from the start, which then ran twice at ~50 evaluations each. Default
        on. Measured (docs/tracking.md "Twenty-seventh session"): the pair terms evaluated
        on the three people's scene 0.62x in total and 0.30x in its heaviest scan; over the
        harness 17 mover-runs sooner and 14 later, switches 38 / 33 -> 38 / 30.
    """

    gate_m: float = 0.6
    gate_chi2: float = 13.8
    merge_m: float = 0.38
    share_m: float = 0.15
    assign_likelihood: bool = True
    coalesce_m: float = 0.25
    coalesce_seen_apart: bool = True
    merge_seen_apart: bool = True
    merge_hidden_m: float = 0.8
    merge_hidden_extent_m: float = 0.65
    shared_scans: int = 4
    shared_dv_m_s: float = 0.2
    shared_fraction: float = 0.25
    hold_seen_apart: bool = True
    follow_seen_through_m: float = 1.5
    follow_inconsistent_fraction: float = 0.0
    smooth_scan_beams: int = 0
    confirm_scans: int = 2
    confirm_speed_m_s: float = 0.05
    confirm_sure_scans: int = 3
    confirm_sigmas: float = 1.5
    confirm_overlap: float = 0.5
    hold_sliding_lines: bool = True
    max_missed: int = 25
    occluded_scans: int = 25
    window_scans: int = 40
    entropy: str = "renyi"
    sigma_m: float = 0.02
    voxel_m: float = 0.03
    position_sigma_m: float = 0.1
    velocity_sigma_m_s: float = 0.01
    accel_sigma_m_s2: float = 0.05
    max_points: int = 300
    keep_points: bool = False
    voxel_max_points: int = 1200
    warm_search_m_s: float = 0.03
    # voxel entropy, warm start: grid-search levels (points per axis) over +-warm_search_m_s;
    # 9, 9, 9 instead of the cold search's 17, 9, 9: a third less update time; final
    # estimates within 0.002 m/s and 1.1 deg of the finer grid's on the paper scene and the
    # synthetic one (measured, 3 seeds each; two levels only, (9, 9), halves the time but
    # moved one synthetic seed's heading by 5 deg)
    warm_voxel_grid: tuple[int, ...] = (9, 9, 9)
    velocity_fusion: str = "overlap"
    renyi_method: str = "newton"
    newton_recentre: bool = True
    turn_reach_m: float = 0.15
    turn_scans: int = 3
    maneuver_m_s: float = 0.3
    maneuver_scans: int = 6
    maneuver_turn_deg: float = 40.0
    maneuver_late_lag: float = 3.0
    maneuver_stop_lag: bool = True
    maneuver_before: bool = True
    maneuver_after_gap: bool = True
    incidence_weights: bool = True
    renyi_subsample: str = "pairs"
    renyi_pairs: str = "adaptive"
    renyi_all_pairs_scans: int = 6
    box_pairs_speed_m_s: float = 0.2
    reacquire_speed_m_s: float = 0.0
    reacquire_births_m_s: float = 1.5
    reacquire_forget_scans: int = 6
    reacquire_moving: bool = False
    reacquire_gone_only: bool = True
    reacquire_unique_m: float = 0.5
    stitch_turned_m: float = 0.35
    ambiguous_chi2: float = 1.0
    stitch_stopped: bool = True
    follow_supported_m_s: float = 0.1
    window_cut_speed_m_s: float = 0.1
    window_cut_drop_m_s: float = 0.4
    window_cut_reach_m: float = 0.05
    window_cut_occluders: bool = True
    window_cut_mask: str = "edges"
    window_cut_floor: bool = True
    max_speed_m_s: float = 5.0
    debias_sigma_m: float = 0.0
    debias_min_speed_m_s: float = 0.5
    debias_max_cut_fraction: float = 0.5
    round_model: str = "cut"
    round_radius_m: tuple[float, float] = (0.05, 0.5)
    round_max_rms: float = 1.5
    round_max_serial: float = 0.15
    round_max_sd_m_s: float = 0.03
    round_fuse: bool = True
    round_filter_cov: bool = True
    round_warm: bool = True

    def __post_init__(self) -> None:
        require(self.confirm_scans >= 2, "confirm_scans", self.confirm_scans, ">= 2")
        require(self.confirm_sure_scans >= 0, "confirm_sure_scans", self.confirm_sure_scans,
                ">= 0 scans")
        require(0 <= self.confirm_overlap <= 1, "confirm_overlap", self.confirm_overlap,
                "0..1 (0: off)")
        require(self.confirm_sigmas >= 0, "confirm_sigmas", self.confirm_sigmas,
                ">= 0 standard deviations (0: off)")
        require(self.max_missed >= 0, "max_missed", self.max_missed, ">= 0")
        require(self.occluded_scans >= 0, "occluded_scans", self.occluded_scans,
                ">= 0 scans (0: off)")
        require(self.entropy in ("voxel", "renyi"), "entropy", self.entropy, "voxel or renyi")
        require(self.renyi_method in ("nelder-mead", "newton"), "renyi_method",
                self.renyi_method, "nelder-mead or newton")
        require(self.renyi_subsample in ("points", "pairs"), "renyi_subsample",
                self.renyi_subsample, "points or pairs")
        require(self.renyi_pairs in ("window", "all", "adaptive"), "renyi_pairs",
                self.renyi_pairs, "window, all or adaptive")
        require(self.renyi_all_pairs_scans >= 2, "renyi_all_pairs_scans",
                self.renyi_all_pairs_scans, ">= 2 scans")
        require(self.box_pairs_speed_m_s >= 0, "box_pairs_speed_m_s",
                self.box_pairs_speed_m_s, ">= 0 m/s (0: off)")
        require(self.velocity_fusion in FUSIONS, "velocity_fusion",
                self.velocity_fusion, ", ".join(FUSIONS))
        require(self.gate_m > 0, "gate_m", self.gate_m, "> 0 m")
        require(self.reacquire_births_m_s >= 0, "reacquire_births_m_s",
                self.reacquire_births_m_s, ">= 0 m/s (0: off)")
        require(int(self.reacquire_forget_scans) == self.reacquire_forget_scans
                and self.reacquire_forget_scans >= 0, "reacquire_forget_scans",
                self.reacquire_forget_scans, "an integer >= 0 (0: off)")
        require(self.reacquire_unique_m >= 0, "reacquire_unique_m", self.reacquire_unique_m,
                ">= 0 m (0: off)")
        require(self.reacquire_speed_m_s >= 0, "reacquire_speed_m_s", self.reacquire_speed_m_s,
                ">= 0 m/s")
        require(self.gate_chi2 > 0, "gate_chi2", self.gate_chi2, "> 0")
        require(self.follow_seen_through_m >= 0, "follow_seen_through_m",
                self.follow_seen_through_m, ">= 0 m (0: off)")
        require(0 <= self.follow_inconsistent_fraction <= 1, "follow_inconsistent_fraction",
                self.follow_inconsistent_fraction, "0..1 (1: off)")
        require(self.smooth_scan_beams >= 0, "smooth_scan_beams", self.smooth_scan_beams,
                ">= 0 beams (0: off)")
        require(self.merge_m >= 0, "merge_m", self.merge_m, ">= 0 m")
        require(self.merge_hidden_extent_m >= 0, "merge_hidden_extent_m",
                self.merge_hidden_extent_m, ">= 0 m")
        require(self.merge_hidden_m >= 0, "merge_hidden_m", self.merge_hidden_m, ">= 0 m (0: off)")
        require(self.coalesce_m >= 0, "coalesce_m", self.coalesce_m, ">= 0 m")
        require(self.shared_scans >= 0, "shared_scans", self.shared_scans, ">= 0 scans (0: off)")
        require(self.shared_dv_m_s >= 0, "shared_dv_m_s", self.shared_dv_m_s, ">= 0 m/s")
        require(0 <= self.shared_fraction <= 1, "shared_fraction", self.shared_fraction, "0..1")
        require(self.share_m >= 0, "share_m", self.share_m, ">= 0 m")
        require(self.turn_reach_m >= 0, "turn_reach_m", self.turn_reach_m, ">= 0 m (0: off)")
        require(self.follow_supported_m_s >= 0, "follow_supported_m_s",
                self.follow_supported_m_s, ">= 0 m/s (0: off)")
        require(self.window_cut_speed_m_s > 0, "window_cut_speed_m_s",
                self.window_cut_speed_m_s, "> 0 m/s (inf: cut slices weigh as any other)")
        require(self.window_cut_drop_m_s > 0, "window_cut_drop_m_s",
                self.window_cut_drop_m_s, "> 0 m/s (inf: never left out)")
        require(self.window_cut_reach_m >= 0, "window_cut_reach_m", self.window_cut_reach_m,
                ">= 0 m (0: the cluster's own ends)")
        require(self.round_model in ("off", "cut", "always"), "round_model",
                self.round_model, "off, cut or always")
        require(len(self.round_radius_m) == 2
                and 0 < self.round_radius_m[0] < self.round_radius_m[1], "round_radius_m",
                self.round_radius_m, "(low, high) with 0 < low < high [m]")
        require(self.round_max_rms > 0, "round_max_rms", self.round_max_rms, "> 0")
        require(-1 <= self.round_max_serial <= 1, "round_max_serial", self.round_max_serial,
                "-1..1 (1: off)")
        require(self.round_max_sd_m_s > 0, "round_max_sd_m_s", self.round_max_sd_m_s,
                "> 0 m/s")
        require(self.window_cut_mask in ("off", "edges", "all"), "window_cut_mask",
                self.window_cut_mask, "off, edges or all")
        require(self.max_speed_m_s > 0, "max_speed_m_s", self.max_speed_m_s,
                "> 0 m/s (inf: any estimate is a measurement)")
        require(self.debias_sigma_m == 0 or self.debias_sigma_m > self.sigma_m,
                "debias_sigma_m", self.debias_sigma_m, f"0 (off) or > sigma_m ({self.sigma_m} m)")
        require(self.debias_min_speed_m_s >= 0, "debias_min_speed_m_s",
                self.debias_min_speed_m_s, ">= 0 m/s")
        require(0 <= self.debias_max_cut_fraction <= 1, "debias_max_cut_fraction",
                self.debias_max_cut_fraction, "0..1")
        require(self.ambiguous_chi2 >= 0, "ambiguous_chi2", self.ambiguous_chi2, ">= 0 (0: off)")
        require(self.turn_scans >= 1, "turn_scans", self.turn_scans, ">= 1")
        require(self.maneuver_m_s >= 0, "maneuver_m_s", self.maneuver_m_s, ">= 0 m/s (0: off)")
        require(self.maneuver_late_lag == 0 or self.maneuver_late_lag > 2,
                "maneuver_late_lag", self.maneuver_late_lag, "0 (off) or > 2")
        require(0 <= self.maneuver_turn_deg < 180, "maneuver_turn_deg", self.maneuver_turn_deg,
                "0 (off) to < 180 deg")
        require(int(self.maneuver_scans) == self.maneuver_scans and self.maneuver_scans >= 3,
                "maneuver_scans", self.maneuver_scans, "an integer >= 3")
        require(self.window_scans >= 2, "window_scans", self.window_scans, ">= 2")
        require(self.max_points >= 3 and self.voxel_max_points >= 3, "max_points",
                (self.max_points, self.voxel_max_points), ">= 3 points")
        for name in ("position_sigma_m", "velocity_sigma_m_s", "accel_sigma_m_s2"):
            require(getattr(self, name) > 0, name, getattr(self, name), "> 0")
        require(len(self.warm_voxel_grid) >= 1 and all(int(n) == n and n >= 3
                                                       for n in self.warm_voxel_grid),
                "warm_voxel_grid", self.warm_voxel_grid, "one or more integers >= 3")


@dataclass(frozen=True)
class TrackState:
    """A track's state after an update.

    Attributes
    ----------
    track_id, scan : int
    t_s : float
        Time of the state (the latest cluster's mean beam time) [s].
    x_m, y_m : float
        Filtered ground-plane position [m].
    v_m_s, heading_rad : float
        Filtered speed [m/s] and heading [rad] (nan before a velocity was measured).
    cov : (4, 4) float
        Covariance of (x, y, vx, vy) [m, m/s].
    n_scans, n_points : int
    confirmed, alive : bool
    """

    track_id: int
    scan: int
    t_s: float
    x_m: float
    y_m: float
    v_m_s: float
    heading_rad: float
    cov: np.ndarray
    n_scans: int
    n_points: int
    confirmed: bool
    alive: bool = True

    def to_dict(self) -> dict:
        """JSON-friendly dict (heading also in degrees)."""
        return {"track": self.track_id, "scan": self.scan, "t_s": round(self.t_s, 4),
                "x_m": round(self.x_m, 4), "y_m": round(self.y_m, 4),
                "v_m_s": None if np.isnan(self.v_m_s) else round(self.v_m_s, 4),
                "heading_deg": None if np.isnan(self.heading_rad)
                else round(float(np.degrees(self.heading_rad)), 3),
                "cov": np.round(self.cov, 8).tolist(), "n_scans": self.n_scans,
                "n_points": self.n_points, "confirmed": self.confirmed, "alive": self.alive}


# (x, vx, y, vy) (Stone Soup's order) <-> (x, y, vx, vy) (TrackState's)
_PERM = np.array([0, 2, 1, 3])
_EPOCH = _dt.datetime(2000, 1, 1, tzinfo=_dt.UTC)


_TAKEN_SCANS = 60  # the online segmenter's window: static support older than it is forgotten
_BIRTH_SIGMA_V_M_S = 0.5  # velocity sigma of a new track: a person walks at most ~1.5 m/s (3 sigma)
_SURE_SIGMAS = 3.0  # a track surely moves when its speed is this many sigmas from zero
# coalesce_seen_apart: tracks followed this many scans each (a piece of one person that a
# noisy beam split off is a new track of one sighting, and still ends)
_KEPT_APART_SCANS = 6
_HOLD_M = 0.15  # hold_seen_apart: a cluster this near a track's prediction holds it
_WEAK_WIDER_M = 0.1  # follow_inconsistent_fraction: a cluster at most this wider than the last
#: hold_sliding_lines: a cluster is a line where its top view's minor spread is at most this
#: fraction of its major one (a table's face: 0.04-0.07; a person's front arc: ~0.4)
_LINE_THIN = 0.15
_LINE_SCANS = 3
#: hold_sliding_lines: the line is its dominant line's inliers when they are at least this
#: fraction of the points (within 3 robust sigmas of it, or this far [m])
_LINE_INLIERS = 0.8
_LINE_INLIER_M = 0.03
_LENGTH_TOL_M = 0.05
#: confirm_overlap: a sighting's point is on the other sightings within this [m] (the range
#: noise and the beam spacing at 4-5 m are 3-4 cm)
_OVERLAP_M = 0.1
_OBJECT_M = 0.5  # follow_seen_through, _inconsistent_fraction: an object's points lie within
# this of its centroid
_COLUMN_M = 0.2  # occluded_scans: a person's radius, about a track's predicted position
_COLUMN_MARGIN_M = 0.15  # occluded_scans: a beam ends this far before the column, or beyond
# follow_seen_through: the fraction of a cluster's beams that must see through the track's
# voxels. An object walking straight away is behind where it was on nearly every beam
# (measured: 0.78-1.0); rays beside a start-up ghost's furniture edge reach a few beams of
# what is behind it (0.56 on 5 of 9 beams, which then took a person's points 50 scans on)
_THROUGH_FRACTION = 0.75
_FORGET_VAR_M2_S2 = 100.0  # a prior velocity variance that carries no information (10 m/s sigma)


def stone_soup_time(t_s: float) -> _dt.datetime:
    """The timestamp the tracker's Stone Soup states carry for time ``t_s`` [s]: a fixed
    epoch (2000-01-01 UTC) plus ``t_s`` (Stone Soup's models take the time between
    states from these; the evaluation's GOSPA states use the same clock)."""
    return _EPOCH + _dt.timedelta(seconds=float(t_s))


#: sightings of a new track in which it may still continue a lost moving track (Tracker._stitch)
_STITCH_SCANS = 4


@dataclass
class _Track:
    track_id: int
    points: list = field(default_factory=list)
    times: list = field(default_factory=list)
    mirrors: list = field(default_factory=list)
    truth: list = field(default_factory=list)
    weights: list = field(default_factory=list)
    sigma: list = field(default_factory=list)  # per scan, (k,): each point's range noise [m]
    # the last round fit that held, and the number of scans the track had then (the next
    # scan's fit starts from it: TrackerConfig.round_warm)
    round_last: tuple | None = None
    # whether the last round fit found a circle (radius, RMS and serial gates): True,
    # False (also: no circle at all from 200 points or more), or None before any fit
    round_shape: bool | None = None
    cut: list = field(default_factory=list)  # per scan, (k, 2, 2): each cut line's bearing
    # as (sin, cos), or NaN
    edges: list = field(default_factory=list)  # per scan, (k, 2, 6): segment.cut_edges
    sensor_v: list = field(default_factory=list)  # per scan, (2,): the sensor's velocity
    # per scan, (j,): the top-view lengths [m] of the slices with both ends the object's
    # outline (hold_sliding_lines, before the track moved)
    outline_len: list = field(default_factory=list)
    scans: list = field(default_factory=list)
    centroids: list = field(default_factory=list)
    t_centroids: list = field(default_factory=list)
    # per scan, (2,): the centroid of the slices no edge cut (NaN: fewer than 3 points)
    centroids_uncut: list = field(default_factory=list)
    last_scan: int = 0
    n_points: int = 0
    motion: MotionEstimate | None = None
    coarse: MotionEstimate | None = None
    state: Any = None  # stonesoup GaussianState (x, vx, y, vy)
    start: int = 0  # index in the lists where the current motion starts (after a turn)
    hidden: int = 0  # scans since last seen in which its predicted place was hidden
    # a track seen once: when [s] the latest scan that looked at its place found something
    # there; None if that scan found it free, or none looked (TrackerConfig.reacquire_gone_only)
    place_there: float | None = None
    moved: bool = False  # its speed reached confirm_speed_m_s once (TrackerConfig)
    parent: int | None = None  # a lost moving track this new one may continue (stitch)
    # index of the sighting with which a track seen once was re-acquired after a gap
    # (TrackerConfig.reacquire_forget_scans); -1: never
    reacquired: int = -1
    # a restart held for the next sighting to confirm (TrackerConfig.maneuver_late_lag:
    # the line lagged more than twice, or a line with two cut sightings proposed it):
    # (the number of sightings when it was seen, the start it would take)
    late: tuple[int, int] | None = None
    # per sighting, (2,): the filtered velocity before it was taken, where the motion
    # window then held maneuver_scans sightings or more (NaN: not settled; the
    # maneuver test's reference, Tracker._maneuvered)
    v_before: list = field(default_factory=list)

    @property
    def cov(self) -> np.ndarray:
        return np.asarray(self.state.covar, float)[np.ix_(_PERM, _PERM)]

    @property
    def x(self) -> np.ndarray:
        """Filtered (x, y, vx, vy)."""
        return np.asarray(self.state.state_vector, float).ravel()[_PERM]


def _speed_changed(new: np.ndarray, old: np.ndarray, by_m_s: float,
                   turn_deg: float = 0.0) -> bool:
    """Whether the speed of velocity ``new`` (2,) [m/s] differs from that of ``old`` by
    more than ``by_m_s`` and by more than a factor of two (a stop or a start), or, with
    ``turn_deg`` > 0, the velocity by more than ``by_m_s`` and its heading by more than
    ``turn_deg`` [deg] at a speed kept within a factor of two (a turn)."""
    a, b = float(np.hypot(*new)), float(np.hypot(*old))
    if min(a, b) < 0.5 * max(a, b):
        return abs(a - b) > by_m_s
    if turn_deg <= 0 or float(np.hypot(*(new - old))) <= by_m_s:
        return False
    cos = float(new @ old) / (a * b)
    return cos < float(np.cos(np.radians(turn_deg)))


def _agrees(est: np.ndarray, vc: np.ndarray, v: np.ndarray, tol_m_s: float,
            standing_m_s: float, lag_max: float = 2.0, stop: bool = True) -> bool:
    """Whether a maneuver's entropy estimate ``est`` (2,) [m/s] of its latest sightings
    confirms the centroids' line-fit velocity ``vc`` against the filtered ``v``: within
    ``tol_m_s`` of it; or, for a start from standing (``v`` slower than ``standing_m_s``),
    a turn at one speed (``est`` within 30 % of ``v``'s speed) or, with ``stop``, a stop
    (``est`` under 30 % of it), beyond ``vc`` along the same change (within 30 deg), up
    to ``lag_max`` times as far from ``v``. The line fit lags a change it spans only
    partly: a start three of its six sightings ago reads 0.63 of the new velocity
    (11/17.5), two ago 0.37; the latest sightings alone read it whole. Not for a change
    of speed while moving: a box leaving the view read a doubling in both."""
    if float(np.hypot(*(est - vc))) <= tol_m_s:
        return True
    s_v, s_e = float(np.hypot(*v)), float(np.hypot(*est))
    if not (s_v < standing_m_s or abs(s_e - s_v) <= 0.3 * s_v or (stop and s_e <= 0.3 * s_v)):
        return False
    dc, de = vc - v, est - v
    nc, ne = float(np.hypot(*dc)), float(np.hypot(*de))
    return nc > 0 and nc <= ne <= lag_max * nc and \
        float(dc @ de) >= np.cos(np.radians(30.0)) * nc * ne


def _debiased(P: np.ndarray, Tp: np.ndarray, mo: MotionEstimate, cfg: TrackerConfig,
              kw: dict[str, Any]) -> MotionEstimate:
    """``mo``'s speed (the refinement with the kernel ``cfg.sigma_m``) extrapolated to a
    zero-width kernel from a second refinement with ``cfg.debias_sigma_m`` (warm from
    ``mo``): the kernel-smoothed sum reads a passing object slow by an amount about linear
    in the kernel's width (range noise widens it), so ``s0 = s1 + (s1 - s2) w1 / (w2 - w1)``
    for the speeds ``s`` read with kernel widths ``w``. The heading and covariance stay
    ``mo``'s (the bias is along the motion). Without a second estimate (it ran off), ``mo``.
    ``P`` (n, 3) [m], ``Tp`` (n,) [s] and ``kw`` as for :func:`_refine_window`."""
    m2 = refine_motion(P, Tp, mo, search_m_s=cfg.warm_search_m_s,
                       **dict(kw, sigma_m=cfg.debias_sigma_m))
    if not m2.v_m_s <= cfg.max_speed_m_s:
        return mo
    k = cfg.sigma_m / (cfg.debias_sigma_m - cfg.sigma_m)
    return replace(mo, v_m_s=max(0.0, mo.v_m_s + k * (mo.v_m_s - m2.v_m_s)))


#: range noise [m] for the round model's residuals when the tracker has no lidar's
#: range_sigma (the URG-04LX's figure below 1 m)
_ROUND_SIGMA_M = 0.01


def _round(tr: _Track, w0: int, keep: np.ndarray, P: np.ndarray, Tp: np.ndarray,
           sizes: list[int], mo: MotionEstimate, cfg: TrackerConfig,
           ce: np.ndarray | None = None, scale: float = 1.0) -> MotionEstimate:
    """``mo`` with the velocity of a moving circle fitted to the track's window (scans from
    ``w0`` of ``sizes`` points each; those where ``keep``: ``P`` (n, 3) [m] at ``Tp`` (n,)
    [s]) where the fit holds (TrackerConfig.round_model), else ``mo`` as it is. ``ce``
    (2, 2): the refinement's covariance per window, ``scale`` times smaller than
    ``mo.cov`` (Rényi: the points in the sum); the fused covariance goes back to
    ``mo.cov``'s scale (TrackerConfig.round_filter_cov)."""
    scans = np.repeat(np.arange(len(sizes)), sizes)[keep]
    last = tr.round_last
    fit = fit_moving_circle(P[:, :2], Tp, float(Tp.max()), mo.velocity,
                            np.concatenate(tr.sigma[w0:])[keep],
                            labels=np.concatenate(tr.mirrors[w0:])[keep], scans=scans,
                            max_radius_m=4 * cfg.round_radius_m[1],
                            start=last[1] if cfg.round_warm and last is not None
                            and last[0] == len(tr.scans) - 1 else None)
    tr.round_last = None
    shape = fit is not None and bool(
        cfg.round_radius_m[0] <= fit.radius_m <= cfg.round_radius_m[1]
        and fit.rms_norm <= cfg.round_max_rms and fit.serial <= cfg.round_max_serial)
    if fit is not None or len(P) >= 200:  # a few points say nothing of the shape
        tr.round_shape = shape
    if not shape or fit is None or not np.sqrt(np.linalg.eigvalsh(fit.cov)[-1]) <= cfg.round_max_sd_m_s:
        return mo
    tr.round_last = (len(tr.scans), fit)
    vel, cov = fit.velocity, mo.cov
    if cfg.round_fuse and ce is not None:
        # both estimates of one window, each at its own covariance: where the entropy
        # reads the motion well (a far object's many scans) it keeps its weight, where it
        # is flat (across a cut) the circle decides
        wi_e, wi_c = np.linalg.inv(ce), np.linalg.inv(fit.cov)
        vel = np.linalg.solve(wi_e + wi_c, wi_e @ mo.velocity + wi_c @ fit.velocity)
        if cfg.round_filter_cov:  # the filter takes what the fused measurement holds
            cov = np.linalg.inv(wi_e + wi_c) * scale
    v, h = motion_from_velocity(vel)
    return replace(mo, v_m_s=v, heading_rad=h, cov=cov)


def _refine_window(P: np.ndarray, Tp: np.ndarray, warm: MotionEstimate | None,
                   coarse: MotionEstimate, cfg: TrackerConfig,
                   **kw: Any) -> MotionEstimate | None:
    """A track window's velocity measurement: the entropy refinement of its points ``P``
    (n, 3) [m] at times ``Tp`` (n,) [s], warm from the previous one ``warm`` (a small
    search around it) or cold from the centroid line ``coarse``; ``kw`` the rest of
    :func:`~nodlidar.tracking.motion.refine_motion`'s arguments.

    A result faster than ``cfg.max_speed_m_s`` is the minimiser run off, not motion: the
    warm start was so far from the motion that no pair of points near it spans two scans
    and the cost was flat (169 m/s measured, warm from a wrong velocity after a mover
    turned in the nod's blind part). The warm result is then replaced by a cold one, and
    if that runs off too there is no measurement (None).
    """
    mo = None
    if warm is not None:
        mo = refine_motion(P, Tp, warm, search_m_s=cfg.warm_search_m_s,
                           voxel_grid=cfg.warm_voxel_grid, **kw)
    if mo is None or not mo.v_m_s <= cfg.max_speed_m_s:
        mo = refine_motion(P, Tp, coarse, search_m_s=0.08, **kw)
    return mo if mo.v_m_s <= cfg.max_speed_m_s else None


class Tracker:
    """Multi-object tracker over segmented scans (module docstring).

    ``update(scan)`` takes a :class:`~nodlidar.tracking.segment.Segmented` scan, or a
    :class:`~nodlidar.tracking.scans.ScanPoints` (segmented here, online, with ``segment``
    and ``range_sigma``), and returns the states of the tracks that changed in this scan
    (updated, or ended).

    Parameters
    ----------
    config : TrackerConfig
    segment : SegmentConfig, optional
    range_sigma : callable, optional
        The lidar's ``range_sigma_m(r)`` for the online segmenter's carving margin.
    """

    def __init__(self, config: TrackerConfig = TrackerConfig(), segment: SegmentConfig | None = None,
                 range_sigma: Callable[[np.ndarray], np.ndarray | float] | None = None) -> None:
        self.config = config
        self.tracks: dict[int, _Track] = {}
        self.ended: list[_Track] = []
        self._next_id = 1
        self._segment = segment
        self._range_sigma = range_sigma
        self._segmenter: OnlineSegmenter | None = None
        from .segment import SegmentConfig
        from .voxels import VoxelGrid

        seg_cfg = segment or SegmentConfig()
        self._grid = VoxelGrid(seg_cfg.voxel_m)
        self._static_age_s = seg_cfg.static_age_s
        self._min_cluster_points = seg_cfg.min_cluster_points
        self._floor_z_m = seg_cfg.ground_z_m + seg_cfg.ground_clearance_m
        # per recent scan: its time [s] and the voxel keys of the points tracks took
        # (follow_supported_m_s: was a supported cluster's support a track's own path?)
        self._taken: list[tuple[float, np.ndarray]] = []
        self._t0_s = np.inf  # the first scan's time [s]: the map's start
        # per pair of track ids (older first): their sightings in a row splitting one
        # cluster, not seen apart and moving alike (TrackerConfig.shared_scans)
        self._shared: dict[tuple[int, int], int] = {}
        self._apart: set[tuple[int, int]] = set()  # pairs of track ids once seen apart
        self._kf: tuple[Any, Any, Any] | None = None  # predictor, updater, LinearGaussian
        # Stone Soup (with the scipy.stats it imports: 0.4-0.9 s) loaded now, not at the
        # first object a live tracker sees - that update took 430 ms, four scan periods
        self._filters()
        import stonesoup.types.detection  # noqa: F401
        import stonesoup.types.hypothesis  # noqa: F401
        import stonesoup.types.state  # noqa: F401

    # -- Stone Soup pieces (imported by the constructor, not by `import`) ---------------
    def _filters(self):
        if self._kf is None:
            from stonesoup.models.measurement.linear import LinearGaussian
            from stonesoup.models.transition.linear import (
                CombinedLinearGaussianTransitionModel,
                ConstantVelocity,
            )
            from stonesoup.predictor.kalman import KalmanPredictor
            from stonesoup.updater.kalman import KalmanUpdater

            q = self.config.accel_sigma_m_s2 ** 2
            tm = CombinedLinearGaussianTransitionModel([ConstantVelocity(q), ConstantVelocity(q)])
            mm = LinearGaussian(4, (0, 2), np.eye(2) * self.config.position_sigma_m ** 2)
            self._kf = (KalmanPredictor(tm), KalmanUpdater(mm), LinearGaussian)
        return self._kf

    def _birth(self, c: np.ndarray, t: float):
        from stonesoup.types.state import GaussianState

        sp, sv = self.config.position_sigma_m, _BIRTH_SIGMA_V_M_S
        return GaussianState(np.array([[c[0]], [0.0], [c[1]], [0.0]]),
                             np.diag([sp ** 2, sv ** 2, sp ** 2, sv ** 2]), timestamp=stone_soup_time(t))

    def _predict(self, tr: _Track, t: float):
        """``tr``'s state predicted to time ``t`` [s]: what the Stone Soup
        :class:`~stonesoup.predictor.kalman.KalmanPredictor` of :meth:`_filters` returns
        (a ``GaussianStatePrediction``, its mean and covariance to the last bit:
        ``tests/test_tracking.py``), with the two constant-velocity blocks written out.
        The predictor builds them with ``block_diag`` per call; the gating predicts every
        track to every cluster, and that took half the tracker's time in a furnished room
        with four people."""
        from stonesoup.types.prediction import Prediction

        pred, _, _ = self._filters()
        prior = tr.state
        ts = stone_soup_time(t)
        dt = (ts - prior.timestamp).total_seconds()
        F = np.eye(4)
        F[0, 1] = F[2, 3] = dt
        a = abs(dt)  # the model's noise grows with |dt| either way
        q = np.array([[a ** 3 / 3, a ** 2 / 2], [a ** 2 / 2, a]])
        q *= self.config.accel_sigma_m_s2 ** 2
        Q = np.zeros((4, 4))
        Q[:2, :2] = Q[2:, 2:] = q
        x = F @ prior.state_vector
        P = F @ prior.covar @ F.T + Q
        return Prediction.from_state(prior, x, P, timestamp=ts,
                                     transition_model=pred.transition_model, prior=prior)

    def _surely_moving(self, tr: _Track, t: float) -> bool:
        """Whether ``tr`` moves at ``follow_supported_m_s`` or faster at time ``t`` [s], and
        surely so: its predicted speed at least ``_SURE_SIGMAS`` standard deviations (along
        its velocity) from zero. A track that has coasted unseen has lost that certainty
        (measured: a start-up ghost on a table, unseen for 2 s at 0.25 m/s, then took the
        table's supported cluster five scans running)."""
        if tr.motion is None:
            return False
        v = tr.x[2:]
        speed = float(np.hypot(*v))
        if speed < self.config.follow_supported_m_s:
            return False
        P = np.asarray(self._predict(tr, t).covar, float)[np.ix_([1, 3], [1, 3])]
        u = v / speed
        return speed >= _SURE_SIGMAS * float(np.sqrt(max(u @ P @ u, 0.0)))

    def _hold(self, seg: Segmented, ids: list, objs: list, cost: np.ndarray, big: float,
              priors: dict, turn_priors: dict) -> None:
        """Forbid (in ``cost``, in place) a track a cluster when its predicted position lies
        on another cluster of the scan, not dynamic, nearer than the first and seen apart
        from it (:func:`~nodlidar.tracking.segment.seen_apart`): the track's object is still
        there, only not seen moving in this scan (TrackerConfig.hold_seen_apart). The
        prediction is the gating's own (``priors``, at the first gated cluster's time)."""
        from scipy.spatial import cKDTree

        scan = seg.scan
        rest = np.flatnonzero((seg.cluster >= 0) & ~seg.dynamic)
        if not len(rest):
            return
        tree = cKDTree(scan.points[rest, :2])
        for a, tid in enumerate(ids):
            cols = np.flatnonzero(cost[a] < big)
            if not len(cols):
                continue
            prior = next((priors[a, int(b)] for b in cols if (a, int(b)) in priors), None)
            if prior is None:  # turn pairs only: their prior is the cluster, not a prediction
                prior = self._predict(self.tracks[tid], scan.t_mid_s)
            m = np.asarray(prior.state_vector, float).ravel()[[0, 2]]
            near = tree.query_ball_point(m, _HOLD_M)
            if not near:
                continue
            lab = np.bincount(seg.cluster[rest[near]]).argmax()
            other = np.flatnonzero((seg.cluster == lab) & ~seg.dynamic)
            d_other = float(np.min(np.hypot(*(scan.points[other, :2] - m).T)))
            for b in cols:
                d_b = float(np.min(np.hypot(*(scan.points[objs[b], :2] - m).T)))
                if d_other < d_b and seen_apart(scan, objs[b], other):
                    cost[a, b] = big
                    turn_priors.pop((a, b), None)

    def _sightings_agree(self, tr: _Track) -> bool:
        """Whether the track's velocity lays its latest sighting and its earlier ones (since
        its motion started) on one another (``TrackerConfig.confirm_overlap``): moved back
        along it to the latest sighting's time, the fraction of points within
        ``_OVERLAP_M`` of the other set, in the top view, of the better covered set."""
        frac = self.config.confirm_overlap
        if frac <= 0 or len(tr.scans) - tr.start < 2:
            return True
        from scipy.spatial import cKDTree

        v = tr.x[2:]
        t1 = float(tr.times[-1].mean())
        moved = [p[:, :2] - np.outer(t - t1, v)
                 for p, t in zip(tr.points[tr.start:], tr.times[tr.start:])]
        last, before = moved[-1], np.concatenate(moved[:-1])
        if not len(last) or not len(before):
            return True
        near_last = cKDTree(before).query(last, distance_upper_bound=_OVERLAP_M)[0] < _OVERLAP_M
        near_before = cKDTree(last).query(before, distance_upper_bound=_OVERLAP_M)[0] < _OVERLAP_M
        return max(float(np.mean(near_last)), float(np.mean(near_before))) >= frac

    @staticmethod
    def _line_normal(tr: _Track) -> tuple[np.ndarray, float] | None:
        """The unit normal (2,) of the track's object in the top view, and its minor to major
        spread (the line's direction is that uncertain, in radians), if it is a thin straight
        line whose extent along itself the scans have not shown, else None
        (``TrackerConfig.hold_sliding_lines``). The line: its last ``_LINE_SCANS`` clusters,
        moved back along the track's velocity to the last one's time. Its extent is shown by
        two of those scans with a slice whose two ends are the object's outline, of the same
        length within ``_LENGTH_TOL_M``: a face's true edges. Where the scan line leaves a
        face over its top or at its foot, the slice's length changes with the nod. The line
        is the dominant one's inliers when they are at least ``_LINE_INLIERS`` of the
        points: a face with a stub of the next face at a corner is that face (a table's
        front face seen from a driving robot, ``track-drive-tables``: 0.20 thin with the
        stub of its side, 0.11 without)."""
        seen = [ln for ln in tr.outline_len[-_LINE_SCANS:] if len(ln)]
        for i, a in enumerate(seen):
            for b in seen[i + 1:]:
                if np.any(np.abs(a[:, None] - b[None, :]) <= _LENGTH_TOL_M):
                    return None
        v = tr.x[2:]
        t1 = float(tr.times[-1].mean())
        p = np.concatenate([pts[:, :2] - np.outer(t - t1, v)
                            for pts, t in zip(tr.points[-_LINE_SCANS:], tr.times[-_LINE_SCANS:])])
        if len(p) < 5:
            return None
        # the dominant line: a face with a stub of the next face at a corner (under a fifth
        # of the points) is that face; the stub's points lie off it by more than three
        # robust sigmas of the rest (a person's arc has no such outliers)
        keep = np.ones(len(p), bool)
        for _ in range(2):
            q = p[keep]
            _, vec = np.linalg.eigh(np.cov(q.T))
            r = p @ vec[:, 0]
            mid = float(np.median(r[keep]))
            mad = float(np.median(np.abs(r[keep] - mid)))
            keep = np.abs(r - mid) <= max(3.0 * 1.4826 * mad, _LINE_INLIER_M)
            if np.count_nonzero(keep) < max(5.0, _LINE_INLIERS * len(p)):
                keep[:] = True
                break
        ev, vec = np.linalg.eigh(np.cov(p[keep].T))
        if ev[0] > (_LINE_THIN * _LINE_THIN) * ev[1]:
            return None
        return vec[:, 0], float(np.sqrt(max(ev[0], 0.0) / max(ev[1], 1e-12)))

    def _follow_unseen(self, seg: Segmented, ids: list, assign: dict, objs: list,
                       cents: list, times: list, priors: dict) -> None:
        """Give each track that took nothing in this scan a cluster, not dynamic, that shows
        its object (appended to ``objs``, ``cents``, ``times``, ``assign`` and ``priors`` in
        place): one the scan sees through a moving track's earlier voxels onto
        (``follow_seen_through_m``), or one with some inconsistent points, fewer than a
        birth needs (``follow_inconsistent_fraction``). The cluster is object-sized and within
        the track's gates; of several candidate pairs the nearest to the prediction
        (chi-square) goes first."""
        from .segment import SegmentConfig

        cfg = self.config
        scan, lab = seg.scan, seg.cluster
        through = cfg.follow_seen_through_m > 0
        inc = getattr(seg, "inconsistent", None)  # duck-typed segmentations may lack it
        weak = cfg.follow_inconsistent_fraction < 1.0 and inc is not None
        done = set(assign.values())
        free = [a for a, tid in enumerate(ids) if a not in done
                and (weak or self.tracks[tid].motion is not None)]
        if not free or lab.max(initial=-1) < 0:
            return
        used = np.zeros(int(lab.max()) + 1, bool)
        for i in objs:
            used[lab[i][lab[i] >= 0]] = True
        cand = (lab >= 0) & ~seg.dynamic
        cand[cand] = ~used[lab[cand]]
        if not cand.any():
            return
        xy = scan.points[:, :2]
        ci = np.flatnonzero(cand)
        n_lab = int(lab.max()) + 1
        cnt = np.bincount(lab[ci], minlength=n_lab)
        labels = np.flatnonzero(cnt)
        cent = np.stack([np.bincount(lab[ci], xy[ci, 0], n_lab)[labels],
                         np.bincount(lab[ci], xy[ci, 1], n_lab)[labels]], axis=1) / \
            cnt[labels, None]
        seg_cfg = self._segment or SegmentConfig()
        weak_ok = np.zeros(len(labels), bool)
        if weak and inc is not None:
            n_inc = np.bincount(lab[ci], inc[ci], n_lab)[labels]
            # not a cluster static support judged (furniture that rays pass beside)
            sup = getattr(seg, "supported", None)
            judged = (np.bincount(lab[ci], sup[ci], n_lab)[labels] > 0 if sup is not None
                      else np.zeros(len(labels), bool))
            weak_ok = ~judged & (n_inc >= seg_cfg.min_inconsistent_points) & \
                (n_inc >= cfg.follow_inconsistent_fraction * cnt[labels])
        hits = None
        pairs = []
        for a in free:
            tr = self.tracks[ids[a]]
            moving = through and tr.motion is not None
            # where the track is now, by its velocity (the exact prediction for the few
            # clusters near it only: Stone Soup's predict costs more than this whole test)
            x = tr.x
            m0 = x[:2] + x[2:] * (scan.t_mid_s - tr.t_centroids[-1])
            dist = np.hypot(*(cent - m0).T)
            near = np.flatnonzero(dist <= self._gate_m(tr, scan.t_mid_s) + 0.3)
            # weak evidence only for the cluster nearest the prediction: a nearer one is
            # more likely the track's object, seen without motion evidence (two people
            # side by side: the other person's cluster must not be taken instead)
            nearest = near[np.argmin(dist[near])] if len(near) else -1
            if not moving:
                near = near[(near == nearest) & weak_ok[near]]
            if not len(near):
                continue
            keys = None
            for j in near:
                g = ci[lab[ci] == labels[j]]
                if np.max(np.hypot(*(xy[g] - cent[j]).T)) > _OBJECT_M:
                    continue
                if weak_ok[j] and j == nearest:
                    # and it looks like the track's object: no wider than its last cluster
                    # (two people side by side, one cluster, are not one of them)
                    last = tr.points[-1][:, :2]
                    r_last = float(np.max(np.hypot(*(last - last.mean(axis=0)).T)))
                    if np.max(np.hypot(*(xy[g] - cent[j]).T)) > r_last + _WEAK_WIDER_M:
                        continue
                else:
                    if hits is None:
                        live = scan.valid & ~seg.ground
                        hits = unique_keys(self._grid.keys(scan.points[live]))
                    if keys is None:
                        old = [p for p in tr.points if p is not None and len(p)]
                        keys = unique_keys(self._grid.keys(np.concatenate(old))) if old else \
                            np.zeros(0, np.int64)
                        # a voxel this scan also hits is not vacated: rays pass beside an
                        # edge there (a start-up ghost's furniture), not through where a
                        # mover was
                        keys = keys[~np.isin(keys, hits)]
                    sig = self._range_sigma(scan.range_m[g]) if self._range_sigma is not None \
                        else 0.0
                    margin = seg_cfg.margin_voxels * seg_cfg.voxel_m + 3.0 * np.asarray(sig, float)
                    hit = seen_through(scan, g, keys, self._grid, margin, cfg.follow_seen_through_m)
                    if hit.sum() < seg_cfg.min_inconsistent_points or hit.mean() < _THROUGH_FRACTION:
                        continue
                # the track's gates, as for a dynamic cluster (last: the prediction costs most)
                t = float(scan.t_s[g].mean())
                prior = self._predict(tr, t)
                mv = np.asarray(prior.state_vector, float).ravel()
                d = cent[j] - mv[[0, 2]]
                if float(np.hypot(*d)) > self._gate_m(tr, t):
                    continue
                S = np.asarray(prior.covar, float)[np.ix_([0, 2], [0, 2])] + \
                    np.eye(2) * cfg.position_sigma_m ** 2
                d2 = float(d @ np.linalg.solve(S, d))
                if d2 <= cfg.gate_chi2:
                    pairs.append((d2, a, int(j), t, prior))
        taken_a, taken_j = set(), set()
        for _, a, k, t, prior in sorted(pairs, key=lambda p: p[0]):
            if a in taken_a or k in taken_j:
                continue
            taken_a.add(a)
            taken_j.add(k)
            objs.append(ci[lab[ci] == labels[k]])
            cents.append(cent[k])
            times.append(t)
            assign[len(objs) - 1] = a
            priors[a, len(objs) - 1] = prior

    def _reacquire(self, seg: Segmented, ids: list, births: list, objs: list, cents: list,
                   times: list, members: dict, priors: dict, turned: set,
                   pending: dict, ambiguous: AbstractSet[int] = frozenset()) -> list:
        """Give lone tracks the new clusters they continue (``reacquire_births_m_s``;
        ``members``, ``priors`` and ``turned`` in place). A moving track's new cluster
        (``stitch_turned_m``, without ``reacquire_moving``) stays a birth and goes into
        ``pending`` (birth -> track id): the new track continues it only if their motions
        meet (:meth:`_stitch`). Returns the births left."""
        cfg = self.config
        scan = seg.scan
        lone = [a for a, tid in enumerate(ids) if a not in members
                and self.tracks[tid].last_scan < scan.scan and (
                    self.tracks[tid].motion is None or (
                        (cfg.reacquire_moving or cfg.stitch_turned_m > 0)
                        and scan.scan - self.tracks[tid].last_scan > cfg.turn_scans))]
        if not lone or not births:
            return births
        lab = getattr(seg, "cluster", None)
        xy = scan.points[:, :2]
        claims: dict[int, list[int]] = {}  # birth -> the lone tracks it may continue
        lone_pending: dict[int, int] = {}  # birth -> the lone track it may be (ambiguous)
        for a in lone:
            tr = self.tracks[ids[a]]
            d = np.hypot(*(xy - tr.centroids[-1]).T)
            unique = cfg.reacquire_unique_m > 0 and tr.motion is None
            near: list[tuple[float, int]] = []  # (jump, birth) within reach
            for b in births:
                dt = times[b] - tr.t_centroids[-1]
                # a moving track's object turned at its own speed (within its gate); one
                # that stood still may have walked off at any walking speed
                sp = float(np.hypot(*tr.x[2:]))
                reach = (cfg.reacquire_births_m_s * dt if tr.motion is None
                         else max(sp * dt + cfg.gate_m, cfg.reacquire_births_m_s * dt
                                  if cfg.stitch_stopped and sp < cfg.confirm_speed_m_s
                                  else 0.0))
                jump = float(np.hypot(*(cents[b] - tr.centroids[-1])))
                if jump > reach:
                    continue
                if cfg.reacquire_gone_only and len(tr.scans) == 1 and \
                        tr.place_there is not None and dt > 0 and \
                        jump / dt * (tr.place_there - tr.t_centroids[-1]) > \
                        2 * _COLUMN_M + _COLUMN_MARGIN_M:
                    # at the speed this continuation implies, the object (itself up to a
                    # column wide) had left the column when a scan found something still
                    # there: a ghost on something static
                    continue
                near.append((jump, b))
            if unique and near:
                # the moving objects that appeared since ``tr`` was seen: these births, and
                # the clusters of tracks born since. Two or more about as near as the
                # nearest: one sighting gives no velocity to tell them apart, so each
                # birth among them is a new track pending on ``tr`` and the one whose own
                # path passes through the sighting continues it (_stitch)
                reach = cfg.reacquire_births_m_s * (scan.t_mid_s - tr.t_centroids[-1])
                taken = [float(np.hypot(*(cents[b] - tr.centroids[-1])))
                         for a2, bs in members.items()
                         if self.tracks[ids[a2]].t_centroids[0] > tr.t_centroids[-1]
                         for b in bs]
                j0 = min([j for j, _ in near] + [j for j in taken if j <= reach])
                band = [b for j, b in near if j <= j0 + cfg.reacquire_unique_m]
                if len(band) + sum(j0 <= j <= min(reach, j0 + cfg.reacquire_unique_m)
                                   for j in taken) >= 2:
                    for b in band:
                        lone_pending.setdefault(b, ids[a])
                    continue
            for _, b in near:
                if lab is not None:
                    # no other cluster of the scan (dynamic or not, taken or not) nearer to
                    # where the track was: its object may be there, only not moving in this
                    # scan, or in a cluster another track took, or in the furniture it
                    # was a ghost on
                    other = (lab >= 0) & ~np.isin(lab, lab[objs[b]])
                    if other.any() and float(d[other].min()) < float(d[objs[b]].min()):
                        continue
                claims.setdefault(b, []).append(a)
        got = []
        for b, cl in claims.items():
            if len(cl) == 1 and cl[0] in ambiguous and not cfg.reacquire_moving:
                pending[b] = ids[cl[0]]  # each candidate: the best-meeting one continues it
                continue
            if len(cl) != 1 or sum(cl[0] in c for c in claims.values()) != 1:
                continue  # ambiguous: a track seen once has only its place to go by
            a = cl[0]
            if self.tracks[ids[a]].motion is not None and not cfg.reacquire_moving:
                pending[b] = ids[a]  # decided on the new track's own motion (_stitch)
                continue
            members[a] = [b]
            if self.tracks[ids[a]].motion is None:
                priors[a, b] = self._predict(self.tracks[ids[a]], times[b])
                self.tracks[ids[a]].reacquired = len(self.tracks[ids[a]].scans)
            else:  # beyond its motion's gates: it turned unseen, its motion starts afresh
                priors[a, b] = self._birth(cents[b], times[b])
                turned.add((a, b))
            got.append(b)
        for b, tid in lone_pending.items():
            if b not in got:
                pending.setdefault(b, tid)
        return [b for b in births if b not in got]

    def _drop_ambiguous_lone(self, scan: ScanPoints, ids: list, assign: dict[int, int],
                             cents: list, n_dyn: int) -> None:
        """Take from ``assign`` (cluster -> track index, in place) the clusters given to a
        track seen once and unseen for more than ``turn_scans`` scans when another moving
        object that appeared since (a dynamic cluster no track took, or one a track born
        since took) is nearer to the track's place than the cluster, or at most
        ``reacquire_unique_m`` [m] farther: either could be its object (TrackerConfig).
        The cluster is then a birth, and :meth:`_reacquire` decides."""
        cfg = self.config
        for b, a in list(assign.items()):
            tr = self.tracks[ids[a]]
            if tr.motion is not None or scan.scan - tr.last_scan <= cfg.turn_scans:
                continue
            jump = float(np.hypot(*(cents[b] - tr.centroids[-1])))
            for b2 in range(n_dyn):
                if b2 == b or (b2 in assign and self.tracks[ids[assign[b2]]].t_centroids[0]
                               <= tr.t_centroids[-1]):
                    continue
                if float(np.hypot(*(cents[b2] - tr.centroids[-1]))) <= \
                        jump + cfg.reacquire_unique_m:
                    del assign[b]
                    break

    def _forget_before_gap(self, tr: _Track) -> None:
        """Drop the sighting before the gap from the motion window of ``tr``, re-acquired
        after it (``reacquire_births_m_s``), if the entropy estimate of the sightings since
        alone differs from its filtered velocity by more than ``maneuver_m_s / 2``: the one
        sighting before, that only started the velocity, was another object, or the same
        one at another speed (``reacquire_forget_scans``). Else ``tr`` is left as it was
        (the long baseline kept)."""
        before = (tr.start, tr.motion, tr.coarse)
        v = tr.x[2:].copy()
        tr.start, tr.motion = tr.reacquired, None
        self._estimate(tr)
        if tr.motion is not None and \
                float(np.hypot(*(tr.motion.velocity - v))) > self.config.maneuver_m_s / 2:
            tr.motion = None  # estimated afresh from the new start
            return
        tr.start, tr.motion, tr.coarse = before

    def _maneuvered(self, tr: _Track) -> tuple[np.ndarray, bool, np.ndarray] | None:
        """The least-squares velocity (2,) [m/s] of the centroids of ``tr``'s last
        ``maneuver_scans`` sightings (this one added), all since its motion last started
        (with ``maneuver_after_gap``, only those since its last gap longer than they span,
        if at least ``(maneuver_scans - 1) // 2 + 2``), of the slices no edge cut (a view's
        or window's edge, an occluder: an object seen in part moves its centroid), in all
        but one of them; if against it ``tr``'s speed more than halved or doubled, by more
        than ``maneuver_m_s``, or its heading turned by more than ``maneuver_turn_deg`` at
        one speed (:class:`TrackerConfig`) - against the filtered velocity, or with
        ``maneuver_before`` the settled one before the line's first sighting - with False
        (True where two of them were cut: a restart's proposal only,
        ``maneuver_late_lag``) and that velocity (2,) [m/s]. Else None."""
        cfg = self.config
        m = int(cfg.maneuver_scans)
        if cfg.maneuver_m_s <= 0 or tr.motion is None or len(tr.scans) - tr.start < m:
            return None
        C = np.asarray(tr.centroids_uncut[-m:])
        tt = np.asarray(tr.t_centroids[-m:])
        n = m  # the line's sightings
        if cfg.maneuver_after_gap:
            # only the sightings since the track was last unseen for longer than the line
            # spans (the nod's blind part): across it, the line mixes the motion before
            # with the one after (TrackerConfig.maneuver_after_gap)
            dt = np.diff(tt)
            gap = np.flatnonzero(dt > (m - 1) * float(np.median(dt)))
            if len(gap):
                k = int(gap[-1]) + 1
                if m - k < (m - 1) // 2 + 2:
                    return None
                C, tt, n = C[k:], tt[k:], m - k
        ok = np.isfinite(C[:, 0])
        n_ok = int(np.count_nonzero(ok))
        if n_ok < n - (2 if cfg.maneuver_late_lag > 0 else 1):
            return None
        C, tt = C[ok], tt[ok]
        tt = tt - tt.mean()
        s = float(tt @ tt)
        if s <= 0:
            return None
        vc = tt @ (C - C.mean(axis=0)) / s
        # stopped or started: the speed more than halved or doubled; or turned at one
        # speed (maneuver_turn_deg; a turn beyond the gates is turn_reach_m's)
        v = tr.x[2:]
        if _speed_changed(vc, v, cfg.maneuver_m_s, cfg.maneuver_turn_deg):
            return vc, n_ok < n - 1, v
        # or against the settled velocity before the line's first sighting: the filter
        # has taken in part of the change since (TrackerConfig.maneuver_before). That
        # sighting lies n or more after the motion's start, so its entry was written
        # after any restart that kept earlier sightings (they keep at most 3)
        if cfg.maneuver_before and len(tr.scans) - tr.start >= 2 * n:
            v = tr.v_before[-n]
            if np.all(np.isfinite(v)) and _speed_changed(vc, v, cfg.maneuver_m_s,
                                                         cfg.maneuver_turn_deg):
                return vc, n_ok < n - 1, v
        return None

    def _restarted(self, tr: _Track, vc: np.ndarray, pending_only: bool = False,
                   v_ref: np.ndarray | None = None) -> bool:
        """Whether ``tr``'s motion restarts with its latest ``(maneuver_scans - 1) // 2 +
        1`` sightings (this one added): their own entropy estimate confirms the
        centroids' velocity ``vc`` (:meth:`_maneuvered`): its speed too changed against
        ``v_ref`` (the velocity the line changed from; None: the filtered one), and it is
        within ``maneuver_m_s / 2`` of ``vc``, or beyond it where the line fit lags a
        start, a stop or a turn (:func:`_agrees`); lagging by more than
        twice (up to ``maneuver_late_lag``), it restarts with one sighting fewer, once the
        next sighting confirms it (until then ``tr.late`` holds it). ``pending_only``:
        either agreement is only held for the next sighting to confirm. A centroid
        also moves when the part of the object seen changes (a box's face as the nod
        passes its top); the points' motion does not. If not, ``tr`` is as it was."""
        cfg = self.config
        before = (tr.start, tr.motion, tr.coarse)
        v = (tr.x[2:] if v_ref is None else v_ref).copy()
        tr.start, tr.motion = len(tr.scans) - ((cfg.maneuver_scans - 1) // 2 + 1), None
        self._estimate(tr)
        if tr.motion is not None and _speed_changed(tr.motion.velocity, v, cfg.maneuver_m_s,
                                                    cfg.maneuver_turn_deg):
            est = tr.motion.velocity
            if _agrees(est, vc, v, cfg.maneuver_m_s / 2, cfg.confirm_speed_m_s,
                       stop=cfg.maneuver_stop_lag):
                if pending_only:
                    tr.late = (len(tr.scans), tr.start)
                    tr.start, tr.motion, tr.coarse = before
                    return False
                tr.motion = None  # estimated afresh from the new start, as after a turn
                return True
            if cfg.maneuver_late_lag > 0 and _agrees(est, vc, v, cfg.maneuver_m_s / 2,
                                                     cfg.confirm_speed_m_s,
                                                     lag_max=cfg.maneuver_late_lag,
                                                     stop=cfg.maneuver_stop_lag):
                # the line lags the change by more than twice: it began within the
                # latest sightings' span, the oldest of them (partly) before it. A box's
                # face changing with the nod reads so for one sighting: the next one
                # must confirm it (here, or as a turn beyond the gates)
                if not pending_only and tr.late is not None and \
                        tr.late[0] == len(tr.scans) - 1:
                    tr.start, tr.motion, tr.late = tr.late[1], None, None
                    return True
                tr.late = (len(tr.scans), tr.start + 1)
        tr.start, tr.motion, tr.coarse = before
        return False

    def _stitch(self, tr: _Track) -> _Track | None:
        """Whether ``tr``, a new track, continues the lost moving track ``tr.parent``
        (``TrackerConfig.stitch_turned_m``), tried at each of its first
        ``_STITCH_SCANS`` sightings with a velocity (a velocity from two scans can be far
        off; the new track is not confirmed meanwhile). It does when the two motions meet:
        the parent's path from where it was last seen and the new track's path traced back
        from where it is now come within ``stitch_turned_m`` of each other at one moment
        between the two sightings (the place and time it turned), at speeds within 30 %
        (or 0.1 m/s), plus twice the lost track's speed uncertainty, of each other. Then
        the parent takes the new track's scans (its motion starting afresh with them, as
        after a turn) and the new track, never reported, ends. Returns the parent, or None
        (``tr`` goes on, pending or as its own track).
        """
        par = self.tracks.get(tr.parent) if tr.parent is not None else None
        if par is None or par.last_scan >= tr.scans[0] or len(tr.scans) > _STITCH_SCANS:
            tr.parent = None
            return None
        lone = par.motion is None  # seen once (TrackerConfig.reacquire_unique_m)
        gap = self._lone_gap(par, tr) if lone else self._meeting_gap(par, tr)
        if gap is None:
            return None
        for sib in self.tracks.values():
            if sib is tr:
                continue
            if sib.parent == par.track_id and len(sib.scans) <= _STITCH_SCANS:
                # another new track may continue it too (an ambiguous re-acquisition): the
                # one whose path meets the lost one's nearest does, once each has a motion
                g = (self._lone_gap(par, sib) if lone else self._meeting_gap(par, sib)) \
                    if sib.motion is not None else -1.0
            elif lone and sib.t_centroids and sib.t_centroids[0] > par.t_centroids[-1]:
                # a track seen once may be any object that appeared since: one whose own
                # path passes nearer to the sighting is it, not this one
                g = self._lone_gap(par, sib)
            else:
                continue
            if g is not None and g <= gap:
                return None
        if lone:
            # the sighting stays in the window (a long baseline), as a re-acquisition's
            par.reacquired = len(par.scans)
        else:
            par.start = len(par.scans)
        for name in ("points", "times", "mirrors", "truth", "weights", "sigma", "cut", "edges",
                     "sensor_v", "scans", "centroids", "t_centroids", "centroids_uncut", "v_before"):
            getattr(par, name).extend(getattr(tr, name))
        par.last_scan, par.n_points = tr.last_scan, par.n_points + tr.n_points
        par.motion, par.coarse, par.state, par.hidden = tr.motion, tr.coarse, tr.state, 0
        par.moved = par.moved or tr.moved  # a lone parent never had a speed to confirm it
        if lone:
            # its velocity from the window that holds the sighting too (a long baseline),
            # superseding the new track's own, as a re-acquisition's would
            par.motion = None
            self._estimate(par)
            if par.motion is not None:
                c, t = np.asarray(par.centroids[-1]), par.t_centroids[-1]
                self._update(par, self._birth(c, t), c, par.motion.velocity,
                             self._velocity_noise(par.motion), first_velocity=True)
        tr.parent = None
        del self.tracks[tr.track_id]
        return par

    def _lone_gap(self, par: _Track, tr: _Track) -> float | None:
        """How far [m] from where ``par``, a track seen once, was seen the new track
        ``tr``'s path traced back (at its own velocity) passes at that time, or None beyond
        ``stitch_turned_m`` or without a velocity (:meth:`_stitch`)."""
        if tr.motion is None:
            return None
        p = np.asarray(tr.centroids[-1]) + tr.x[2:] * (par.t_centroids[-1] - tr.t_centroids[-1])
        gap = float(np.hypot(*(p - np.asarray(par.centroids[-1]))))
        return gap if gap <= self.config.stitch_turned_m else None

    def _meeting_gap(self, par: _Track, tr: _Track) -> float | None:
        """How near [m] the lost track ``par``'s path from where it was last seen and the
        new track ``tr``'s path traced back come at one moment between the two sightings,
        or None where they do not meet (:meth:`_stitch`)."""
        cfg = self.config
        if tr.motion is None:
            return None
        p1, t1, v1 = np.asarray(par.centroids[-1]), par.t_centroids[-1], par.x[2:]
        p2, t2, v2 = np.asarray(tr.centroids[-1]), tr.t_centroids[-1], tr.x[2:]
        s1, s2 = float(np.hypot(*v1)), float(np.hypot(*v2))
        # the lost track's speed is as sure as its filter says (seen twice: a few cm/s to
        # tenths of a m/s)
        u1 = v1 / max(s1, 1e-9)
        sd1 = float(np.sqrt(max(float(u1 @ par.cov[2:, 2:] @ u1), 0.0)))
        # the speed may have fallen (it stopped or slowed on its way), or have been
        # anything if it stood still (it walked off); not risen beyond the tolerance
        tol = max(0.3 * s1, 0.1) + 2.0 * sd1
        if t2 <= t1 or (abs(s2 - s1) > tol if not cfg.stitch_stopped else
                        s1 >= cfg.confirm_speed_m_s and s2 - s1 > tol):
            return None
        # the gap between the two paths at time t, A + B (t - t1), closest on [t1, t2]
        a = p1 - (p2 + v2 * (t1 - t2))
        b = v1 - v2
        bb = float(b @ b)
        u = 0.0 if bb <= 0 else float(np.clip(-(a @ b) / bb, 0.0, t2 - t1))
        gap = float(np.hypot(*(a + b * u)))
        return gap if gap <= cfg.stitch_turned_m else None

    def _ambiguous(self, scan: ScanPoints, ids: list, objs: list, cents: list,
                   cost: np.ndarray, priors: dict, big: float) -> set[int]:
        """The moving tracks seen again after the nod's blind part (more than
        ``turn_scans`` scans) whose motion gates two clusters about equally
        (``TrackerConfig.ambiguous_chi2``): their rows of ``cost`` (tracks x clusters) are
        set to ``big`` in place, so that neither cluster is theirs by this scan's cost;
        each becomes a new track pending on them (:meth:`_reacquire`), and the one whose
        motion meets the lost track's path nearest continues it (:meth:`_stitch`). A
        cluster another track predicts better is that one's, not a candidate; two
        candidates are two objects, not two pieces of one: farther apart than a birth
        merges (``merge_m``), with free space seen between them."""
        cfg = self.config
        out: set[int] = set()
        if cfg.ambiguous_chi2 <= 0 or cfg.stitch_turned_m <= 0 or len(objs) < 2:
            return out
        gapped = [a for a, tid in enumerate(ids) if self.tracks[tid].motion is not None
                  and scan.scan - self.tracks[tid].last_scan > cfg.turn_scans]
        if not gapped:
            return out
        low = np.sort(cost, axis=0)  # per cluster, the tracks' costs from the lowest
        second = low[1] if len(ids) > 1 else np.full(len(objs), big)
        for a in gapped:
            other = np.where(cost[a] <= low[0], second, low[0])  # the best other track's
            cand = np.array([b for b in range(len(objs))
                             if (a, b) in priors and cost[a, b] <= other[b]], int)
            if len(cand) < 2:
                continue
            b1, b2 = cand[np.argsort(cost[a][cand])][:2]
            if cost[a, b2] - cost[a, b1] < cfg.ambiguous_chi2 \
                    and float(np.hypot(*(cents[b1] - cents[b2]))) > cfg.merge_m \
                    and self._two_objects(scan, objs[b1], objs[b2]):
                cost[a] = big
                out.add(a)
        return out

    def _hidden(self, tr: _Track, scan: ScanPoints, movers: np.ndarray) -> bool:
        """Whether ``tr``'s predicted place is hidden in ``scan`` behind another track's
        object: at least 3 beams, and more than pass through it, end in front of a
        person-sized column there on points of ``movers`` (beam indices: the clusters the
        tracks took in this scan). The column reaches from the floor (above the ground
        band) to the track's highest point: the object stands on the floor, though it may
        have been seen at some heights only
        (:func:`~nodlidar.tracking.segment.behind_or_through`)."""
        from .segment import SegmentConfig

        pts = [p for p in tr.points if p is not None and len(p)]
        if not pts:
            return False
        top = max(float(p[:, 2].max()) for p in pts)
        sc = self._segment or SegmentConfig()
        x = tr.x  # the mean's constant-velocity prediction (no covariance needed)
        m = x[:2] + x[2:] * (scan.t_mid_s - (tr.state.timestamp - _EPOCH).total_seconds())
        z = (sc.ground_z_m + sc.ground_clearance_m, top)
        # the movers' beams first (few): most scans end there
        n_hidden = len(behind_or_through(scan, m, _COLUMN_M, z, _COLUMN_MARGIN_M, movers)[0])
        return n_hidden >= 3 and n_hidden > behind_or_through(
            scan, m, _COLUMN_M, z, _COLUMN_MARGIN_M)[1]

    def _look_at_place(self, tr: _Track, scan: ScanPoints) -> None:
        """Update ``tr.place_there`` from ``scan``: of the beams that meet a person-sized
        column where ``tr`` was last seen (floor to its highest point), 3 or more, and
        more than pass through, end inside it - something is still there (the scan's
        time); 3 or more, and more than end inside, pass through - it is gone (None)
        (:func:`~nodlidar.tracking.segment.column_rays`). Otherwise unchanged."""
        from .segment import SegmentConfig

        pts = [p for p in tr.points if p is not None and len(p)]
        if not pts:
            return
        sc = self._segment or SegmentConfig()
        z = (sc.ground_z_m + sc.ground_clearance_m, max(float(p[:, 2].max()) for p in pts))
        _, n_through, n_in = column_rays(scan, tr.centroids[-1], _COLUMN_M, z, _COLUMN_MARGIN_M)
        if n_in >= 3 and n_in > n_through:
            tr.place_there = scan.t_mid_s
        elif n_through >= 3 and n_through > n_in:
            tr.place_there = None

    def _gate_m(self, tr: _Track, t: float) -> float:
        """Distance gate [m] of ``tr`` for a cluster at time ``t`` [s]: ``gate_m``, grown
        to ``reacquire_speed_m_s * (t - last seen)`` while the track has no velocity
        (:class:`TrackerConfig`)."""
        cfg = self.config
        if tr.motion is None and cfg.reacquire_speed_m_s > 0:
            return max(cfg.gate_m, cfg.reacquire_speed_m_s * (t - tr.t_centroids[-1]))
        return cfg.gate_m

    def _turn_reach_m(self, tr: _Track, scan: int, t: float) -> float:
        """How far [m] from its last centroid a cluster may be for ``tr`` to take it as
        having turned (``TrackerConfig.turn_reach_m``; 0: not eligible)."""
        cfg = self.config
        if cfg.turn_reach_m <= 0 or tr.motion is None or scan - tr.last_scan > cfg.turn_scans:
            return 0.0
        x = tr.x
        return cfg.turn_reach_m + float(np.hypot(x[2], x[3])) * max(t - tr.t_centroids[-1], 0.0)

    def _velocity_noise(self, mo: MotionEstimate) -> np.ndarray:
        """Measurement noise (2, 2) [m^2/s^2] of a window's velocity estimate ``mo``.

        ``"kalman"``/``"first"``: the refinement's covariance as it is (for Rényi, the
        inverse Hessian of the cost: a curvature, not calibrated) + the floor. ``"overlap"``:
        ``n_scans * C + floor^2`` with ``C`` the calibrated covariance: for Rényi the
        inverse Hessian divided by the points in the sum ``N`` (the cost is ``-ln`` of a mean
        of kernel terms over the points, so its curvature is per point; ``N`` points carry
        ``N`` times it - on the paper scene this brings the 2nd-scan sd from 0.54 to ~0.04 m/s
        and the 22nd's from 0.048 to 0.003 m/s, the size of the estimate's actual error);
        for the voxel entropy the grid's own spread (a resolution, already absolute). The
        factor ``n_scans`` (scans in the window) is the overlap: consecutive windows share
        ``n - 1`` of their ``n`` scans, so fusing every window estimate at its own
        covariance would count each scan ``n`` times; at ``n`` times it, the filter's
        information grows by one scan's per scan, as the data's does.
        """
        cfg = self.config
        vc = np.asarray(mo.cov, float) if mo.cov is not None else np.zeros((2, 2))
        if not np.all(np.isfinite(vc)):
            vc = np.zeros((2, 2))
        floor = np.eye(2) * cfg.velocity_sigma_m_s ** 2
        if cfg.velocity_fusion != "overlap":
            return vc + floor
        if cfg.entropy == "renyi":
            # the points in the sum: all of them when pairs are drawn (measured: the
            # estimate's scatter is then ~1/1.7 of the capped one's, as H^-1 / N says)
            n = mo.n_points if cfg.renyi_subsample == "pairs" else min(mo.n_points, cfg.max_points)
            vc = vc / max(n, 1)
        return max(min(mo.n_scans, cfg.window_scans), 1) * vc + floor

    def _update(self, tr: _Track, prior, c: np.ndarray, vel, vel_cov,
                first_velocity: bool = False) -> None:
        from stonesoup.types.detection import Detection
        from stonesoup.types.hypothesis import SingleHypothesis

        _, upd, LinearGaussian = self._filters()
        cfg = self.config
        if vel is None:
            z = np.array([[c[0]], [c[1]]])
            mm = LinearGaussian(4, (0, 2), np.eye(2) * cfg.position_sigma_m ** 2)
        else:
            z = np.array([[c[0]], [c[1]], [vel[0]], [vel[1]]])
            R = np.zeros((4, 4))
            R[:2, :2] = np.eye(2) * cfg.position_sigma_m ** 2
            if cfg.velocity_fusion == "window" or (cfg.velocity_fusion in ("first", "overlap")
                                                   and first_velocity):
                # the window estimate supersedes the previous one (module docstring): the
                # prior's velocity is forgotten (a variance far above any walking speed's,
                # no correlation with the position)
                from stonesoup.types.state import GaussianState

                P = np.array(prior.covar, float)
                P[[1, 3], :] = 0.0
                P[:, [1, 3]] = 0.0
                P[1, 1] = P[3, 3] = _FORGET_VAR_M2_S2
                prior = GaussianState(prior.state_vector, P, timestamp=prior.timestamp)
            if cfg.velocity_fusion == "window":
                R[2:, 2:] = np.eye(2) * cfg.velocity_sigma_m_s ** 2
            else:
                R[2:, 2:] = vel_cov
            mm = LinearGaussian(4, (0, 2, 1, 3), R)
        det = Detection(z, timestamp=prior.timestamp, measurement_model=mm)
        tr.state = upd.update(SingleHypothesis(prior, det))

    # -- per scan ------------------------------------------------------------------------
    def _state(self, tr: _Track, alive: bool = True) -> TrackState:
        x = tr.x
        has_v = tr.motion is not None
        return TrackState(tr.track_id, tr.last_scan,
                          (tr.state.timestamp - _EPOCH).total_seconds(), float(x[0]),
                          float(x[1]), float(np.hypot(x[2], x[3])) if has_v else float("nan"),
                          float(np.arctan2(x[3], x[2])) if has_v else float("nan"), tr.cov,
                          len(tr.scans), tr.n_points,
                          len(tr.scans) >= self.config.confirm_scans and tr.parent is None
                          and (tr.moved or self.config.confirm_speed_m_s <= 0), alive)

    def _estimate(self, tr: _Track) -> None:
        """Entropy refinement of the track's window (its velocity measurement)."""
        cfg = self.config
        w0 = max(tr.start, len(tr.scans) - cfg.window_scans)  # the window, since any turn
        n_seg = len(tr.scans) - tr.start
        if n_seg < 2:
            return
        C = np.array(tr.centroids[w0:])
        T = np.array(tr.t_centroids[w0:])
        if np.ptp(T) <= 0:
            return
        coarse = tr.coarse = coarse_motion(C, T)
        P = np.concatenate(tr.points[w0:])
        Tp = np.concatenate(tr.times[w0:])
        # slices cut by a window's edge weigh less the faster the track moves across the
        # cut's line, and are left out when it moves fast across it, once the rest spans
        # two scans (TrackerConfig.window_cut_speed_m_s, window_cut_drop_m_s)
        v = tr.x[2:] if tr.motion is not None else coarse.v_m_s * np.array(
            [np.cos(coarse.heading_rad), np.sin(coarse.heading_rad)])
        # across each cut line (a beam's ray, or the floor's line along the scan), which
        # moves with the sensor: relative to the sensor's velocity; per point the fastest
        sizes = [len(b) for b in tr.cut[w0:]]
        sc = np.concatenate(tr.cut[w0:])  # (k, 2 lines, sin / cos)
        du = v - np.repeat(np.array(tr.sensor_v[w0:]).reshape(-1, 2), sizes, axis=0)
        across_lines = np.abs(du[:, :1] * sc[:, :, 0] - du[:, 1:] * sc[:, :, 1])
        across = np.fmax(across_lines[:, 0], across_lines[:, 1])  # NaN: uncut
        keep = ~(across >= cfg.window_cut_drop_m_s)
        # left out only when what is left carries the estimate: most of the window's
        # points, a cluster's worth in two scans. An object entering the view is cut in
        # every slice; its few uncut points per scan gave a velocity of noise (45 deg off)
        kept = np.concatenate([[0], np.cumsum(keep)])[np.cumsum([0] + sizes)]
        if (2 * np.count_nonzero(keep) < len(keep)
                or np.count_nonzero(np.diff(kept) >= self._min_cluster_points) < 2):
            keep[:] = True
        a = across[keep]
        cut_w = np.where(np.isnan(a), 1.0,
                         np.minimum(1.0, cfg.window_cut_speed_m_s / np.maximum(a, 1e-9)))
        P, Tp = P[keep], Tp[keep]
        if len(P) < 3:
            return
        # the Rényi sum over pairs of points seen through the same mirror window
        # (TrackerConfig.renyi_pairs; "adaptive": only while the window is short)
        within = cfg.renyi_pairs == "window" or (
            cfg.renyi_pairs == "adaptive"
            and min(n_seg, cfg.window_scans) < cfg.renyi_all_pairs_scans) or (
            # no circle, and fast: the terms between windows align a box's faces
            # (TrackerConfig.box_pairs_speed_m_s)
            cfg.box_pairs_speed_m_s > 0 and tr.round_shape is False and tr.motion is not None
            and float(np.hypot(tr.x[2], tr.x[3])) >= cfg.box_pairs_speed_m_s)
        wts = None
        if cfg.entropy == "renyi" and (cfg.incidence_weights or np.any(cut_w < 1)):
            wts = (np.concatenate(tr.weights[w0:])[keep] if cfg.incidence_weights
                   else np.ones(len(P))) * cut_w
        lab = (np.concatenate(tr.mirrors[w0:])[keep]
               if cfg.entropy == "renyi" and within else None)
        edges = None
        if cfg.entropy == "renyi" and cfg.window_cut_mask != "off":
            # only slices the track crosses at window_cut_speed_m_s or more: slower, a
            # cut pulls little and its weight is 1
            edges = np.concatenate(tr.edges[w0:])[keep]
            edges[~(across_lines[keep] >= cfg.window_cut_speed_m_s)] = np.nan
        # warm start from the previous refinement (a small search around it), cold from the
        # centroid line: keeps one update well inside the scan period
        kw: dict[str, Any] = dict(entropy=cfg.entropy, sigma_m=cfg.sigma_m,
                                  voxel_m=cfg.voxel_m, n_scans=n_seg,
                                  max_points=cfg.max_points, renyi_method=cfg.renyi_method,
                                  newton_recentre=cfg.newton_recentre,
                                  renyi_subsample=cfg.renyi_subsample,
                                  voxel_max_points=cfg.voxel_max_points, labels=lab,
                                  weights=wts, edges=edges)
        tr.motion = _refine_window(P, Tp, tr.motion, coarse, cfg, **kw)
        if (tr.motion is not None and cfg.entropy == "renyi" and cfg.debias_sigma_m > 0
                and tr.motion.v_m_s >= cfg.debias_min_speed_m_s
                and np.mean(~np.isnan(across)) <= cfg.debias_max_cut_fraction):
            # mostly whole slices: a cut's bias is not the kernel's, and the extrapolation
            # doubles it (TrackerConfig.debias_sigma_m)
            tr.motion = _debiased(P, Tp, tr.motion, cfg, kw)
        if (tr.motion is not None and cfg.round_model != "off"
                and (cfg.round_model == "always" or np.any(~np.isnan(across)))):
            ce, scale = None, 1.0
            if tr.motion.cov is not None and np.all(np.isfinite(tr.motion.cov)):
                # the refinement's own covariance per window (_velocity_noise, without the
                # overlap's factor and the floor): Rényi's inverse Hessian over the points
                # in the sum, the voxel grid's spread as it is
                ce = np.asarray(tr.motion.cov, float)
                if cfg.entropy == "renyi":
                    n = (tr.motion.n_points if cfg.renyi_subsample == "pairs"
                         else min(tr.motion.n_points, cfg.max_points))
                    scale = float(max(n, 1))
                    ce = ce / scale
                if not np.linalg.eigvalsh(ce)[0] > 0:
                    ce = None
            tr.motion = _round(tr, w0, keep, P, Tp, sizes, tr.motion, cfg, ce, scale)

    def _segmented(self, scan: Segmented | ScanPoints) -> Segmented:
        if hasattr(scan, "objects"):  # already segmented (duck-typed, as before)
            return cast("Segmented", scan)
        from .segment import OnlineSegmenter, SegmentConfig

        if self._segmenter is None:
            self._segmenter = OnlineSegmenter(self._segment or SegmentConfig(), self._range_sigma)
        return self._segmenter.update(scan)

    def update(self, seg: Segmented | ScanPoints) -> list[TrackState]:
        """Feed one scan (segmented, or ScanPoints); returns the states that changed."""
        from scipy.optimize import linear_sum_assignment

        cfg = self.config
        seg = self._segmented(seg)
        scan = seg.scan
        self._t0_s = min(self._t0_s, scan.t_mid_s)
        objs = seg.objects()
        n_dyn = len(objs)
        if cfg.follow_supported_m_s > 0 and hasattr(seg, "supported_objects"):
            # clusters dynamic only without static support, where that support is the
            # tracks' own earlier points: a moving track may take one (its object is back
            # on its own path); nothing is born from one
            sup = seg.supported_objects()
            path = self._path_keys(scan.t_mid_s) if sup else np.zeros(0, np.int64)
            objs = objs + [i for i in sup if len(path) and np.mean(
                np.isin(self._grid.keys(scan.points[i]), path)) >= 0.5]
        supported = set(range(n_dyn, len(objs)))
        cents = [scan.points[i, :2].mean(axis=0) for i in objs]
        times = [float(scan.t_s[i].mean()) for i in objs]
        ids = list(self.tracks)
        big = 1e9
        s4 = cfg.position_sigma_m ** 4  # det S of a certain prediction: the cost's zero
        cost = np.full((len(ids), len(objs)), big)
        priors: dict[tuple[int, int], Any] = {}
        # turn pairs' priors (a birth at the cluster) are kept apart from the motion
        # predictions: only an assigned turn pair uses one; the sharing test below must see
        # where a track's motion puts it, not the cluster itself
        turn_priors: dict[tuple[int, int], Any] = {}
        for a, tid in enumerate(ids):
            tr = self.tracks[tid]
            moving = bool(supported) and self._surely_moving(tr, scan.t_mid_s)
            for b, (c, t) in enumerate(zip(cents, times)):
                if b in supported and not moving:
                    continue
                prior = self._predict(tr, t)
                m = np.asarray(prior.state_vector, float).ravel()
                P = np.asarray(prior.covar, float)
                d = c - m[[0, 2]]
                if float(np.hypot(*d)) <= self._gate_m(tr, t):
                    S = P[np.ix_([0, 2], [0, 2])] + np.eye(2) * cfg.position_sigma_m ** 2
                    d2 = float(d @ np.linalg.solve(S, d))
                    if d2 <= cfg.gate_chi2:
                        # the pair's negative log-likelihood (up to a constant): a track
                        # whose prediction is vague does not win a cluster from one whose
                        # prediction is sure only by being, by chance, nearer in its own
                        # sigmas (TrackerConfig.assign_likelihood)
                        cost[a, b] = d2 + (float(np.log(np.linalg.det(S) / s4))
                                           if cfg.assign_likelihood else 0.0)
                        priors[a, b] = prior
                        continue
                if b in supported:
                    continue  # a moving track's gate only (no turns)
                reach = self._turn_reach_m(tr, scan.scan, t)
                dl = float(np.hypot(*(c - tr.centroids[-1])))
                if reach > 0 and dl <= reach:
                    cost[a, b] = cfg.gate_chi2 + (dl / reach) ** 2
                    turn_priors[a, b] = self._birth(c, t)
        ambiguous = self._ambiguous(scan, ids, objs, cents, cost, priors, big)
        if cfg.hold_seen_apart and len(ids) and len(objs) and \
                getattr(seg, "cluster", None) is not None:
            self._hold(seg, ids, objs, cost, big, priors, turn_priors)
        assign: dict[int, int] = {}
        if len(ids) and len(objs):
            rows, cols = linear_sum_assignment(cost)
            assign = {int(b): int(a) for a, b in zip(rows, cols) if cost[a, b] < big}
        if cfg.reacquire_unique_m > 0:
            self._drop_ambiguous_lone(scan, ids, assign, cents, n_dyn)
        turned = {(a, b) for b, a in assign.items() if (a, b) in turn_priors}
        for a, b in turned:
            priors[a, b] = turn_priors[a, b]
        # a cluster that gates with other confirmed tracks' predictions too holds (part of)
        # those objects (two people touching in the top view, or one partly behind the
        # other): its points go to the nearest of the predictions
        objs, cents, times = list(objs), list(cents), list(times)
        shares: list[list[tuple[int, int]]] = []  # per shared cluster: (track id, its part)
        origin = list(range(len(objs)))  # each cluster's or part's segmentation cluster
        confirmed = [a for a, tid in enumerate(ids)
                     if len(self.tracks[tid].scans) >= cfg.confirm_scans]
        for b, a0 in list(assign.items()):
            idx = objs[b]
            xy = scan.points[idx, :2]
            others = []
            for a in confirmed:
                if a == a0 or float(np.hypot(*(cents[b] - self.tracks[ids[a]].x[:2]))) > cfg.gate_m:
                    continue
                if (a, b) not in priors:
                    priors[a, b] = self._predict(self.tracks[ids[a]], times[b])
                pa = np.asarray(priors[a, b].state_vector, float).ravel()[[0, 2]]
                # the prediction lies on (or just in front of) the cluster's points
                if float(np.min(np.linalg.norm(xy - pa, axis=1))) <= cfg.share_m:
                    others.append(a)
            if not others:
                continue
            cand = [a0] + others
            parts = [b]
            pred = np.array([np.asarray(priors[a, b].state_vector, float).ravel()[[0, 2]]
                             for a in cand])
            near = np.argmin(np.linalg.norm(xy[:, None, :] - pred[None], axis=2), axis=1)
            for j, a in enumerate(cand[1:], start=1):
                sel = near == j
                if sel.sum() < 3 or (near == 0).sum() < 3:
                    continue
                objs.append(idx[sel])
                cents.append(xy[sel].mean(axis=0))
                times.append(float(scan.t_s[idx[sel]].mean()))
                assign[len(objs) - 1] = a
                parts.append(len(objs) - 1)
                origin.append(b)
                priors[a, len(objs) - 1] = priors[a, b]
                if b in supported:
                    supported.add(len(objs) - 1)
                keep = near != j
                idx, xy, near = idx[keep], xy[keep], near[keep]
            objs[b] = idx
            cents[b] = xy.mean(axis=0)
            shares.append([(ids[assign[x]], x) for x in parts])
        if (cfg.follow_seen_through_m > 0 or cfg.follow_inconsistent_fraction < 1.0) and \
                getattr(seg, "cluster", None) is not None:
            self._follow_unseen(seg, ids, assign, objs, cents, times, priors)
        # leftovers near a track's assigned cluster are pieces of the same object
        members: dict[int, list[int]] = {}
        for b, a in assign.items():
            members.setdefault(a, []).append(b)
        births = []
        for b in range(len(objs)):
            if b in assign or b in supported:
                continue
            near = [(float(np.hypot(*(cents[b] - cents[bb]))), a, bb)
                    for bb, a in assign.items()]
            near = [x[:2] for x in near if self._pieces(scan, objs[b], objs[x[2]], x[0])]
            if near:
                members[min(near)[1]].append(b)
            else:
                births.append(b)
        pending: dict[int, int] = {}
        if cfg.reacquire_births_m_s > 0:
            births = self._reacquire(seg, ids, births, objs, cents, times, members, priors,
                                     turned, pending, ambiguous)
        changed = []
        seen_idx: dict[int, np.ndarray] = {}  # each track's points of this scan
        for a, bs in members.items():
            tr = self.tracks[ids[a]]
            if (a, bs[0]) in turned:
                # the object turned: its motion starts afresh here (TrackerConfig.turn_reach_m),
                # or where the previous sighting's lagging line placed the turn
                late = tr.late
                tr.start = late[1] if late is not None and late[0] == len(tr.scans) \
                    else len(tr.scans)
                tr.motion = None
            idx = np.concatenate([objs[b] for b in bs])
            c = scan.points[idx, :2].mean(axis=0)
            t = float(scan.t_s[idx].mean())
            prior = (priors[a, bs[0]] if len(bs) == 1 or tr.start == len(tr.scans)
                     else self._predict(tr, t))
            self._add(tr, scan, idx, c, t)
            if cfg.reacquire_forget_scans > 0 and tr.start < tr.reacquired and \
                    len(tr.scans) - tr.reacquired == cfg.reacquire_forget_scans:
                self._forget_before_gap(tr)
            man = None if (a, bs[0]) in turned else self._maneuvered(tr)
            # a line with one more cut sighting only proposes a restart: the next
            # sighting must confirm it (maneuver_late_lag)
            if man is not None and self._restarted(tr, man[0], pending_only=man[1],
                                                   v_ref=man[2]):
                # it stopped or started: the window restarts with the sightings since
                # (TrackerConfig.maneuver_m_s)
                prior = self._birth(c, t)
            first = tr.motion is None
            self._estimate(tr)
            mo = tr.motion
            self._update(tr, prior, c, None if mo is None else mo.velocity,
                         None if mo is None else self._velocity_noise(mo),
                         first_velocity=first)
            if not tr.moved and tr.motion is not None:
                # moving: at the confirm speed, surely so while the velocity is only two
                # scans old (a person standing still read 0.05-0.11 +- 0.09 m/s then)
                v = tr.x[2:]
                sp = float(np.hypot(*v))
                u = v / max(sp, 1e-9)
                line = self._line_normal(tr) if cfg.hold_sliding_lines else None
                if line is not None:
                    # a line shows only its motion across itself: along it, its ends place
                    # it, and the top end of a face moves with the nod (furniture); of a
                    # speed along it, as much as the line's direction is uncertain seems to
                    # run across
                    u, dirn = line
                    along = abs(float(v[0] * u[1] - v[1] * u[0]))
                    sp = max(abs(float(v @ u)) - dirn * along, 0.0)
                sd = float(np.sqrt(max(float(u @ tr.cov[2:, 2:] @ u), 0.0)))
                tr.moved = (sp - (sd if len(tr.scans) < cfg.confirm_sure_scans else 0.0)
                            >= cfg.confirm_speed_m_s and sp >= cfg.confirm_sigmas * sd
                            and self._sightings_agree(tr))
            if tr.parent is not None:
                parent = self._stitch(tr)
                if parent is not None:
                    # the new track ends, never confirmed: the lost one goes on
                    changed.append(replace(self._state(tr, alive=False), confirmed=False))
                    tr = parent
            seen_idx[tr.track_id] = idx
            changed.append(self._state(tr))
        # new clusters within merge_m of each other are pieces of one new object
        groups: list[list[int]] = []
        for b in births:
            for g in groups:
                if min(float(np.hypot(*(cents[b] - cents[bb]))) for bb in g) <= cfg.merge_m \
                        and not (cfg.merge_seen_apart
                                 and any(seen_apart(scan, objs[b], objs[bb]) for bb in g)):
                    g.append(b)
                    break
            else:
                groups.append([b])
        for g in groups:
            idx = np.concatenate([objs[b] for b in g])
            c = scan.points[idx, :2].mean(axis=0)
            t = float(scan.t_s[idx].mean())
            tr = _Track(self._next_id)
            self._next_id += 1
            self.tracks[tr.track_id] = tr
            if len(g) == 1 and g[0] in pending:
                tr.parent = pending[g[0]]
            self._add(tr, scan, idx, c, t)
            tr.state = self._birth(c, t)
            seen_idx[tr.track_id] = idx
            st = self._state(tr)
            changed.append(st)
        # a track's path: the dynamic clusters it took once static support could judge
        # them (the map 2 s old). Not supported ones, nor those of the first 2 s: a ghost
        # born on a table's edge at start-up would make the table its own "path"
        taken = [objs[b] for bs in members.values() for b in bs if b not in supported] + \
            [objs[b] for g in groups for b in g]
        if not taken or scan.t_mid_s < self._t0_s + self._static_age_s:
            taken = [np.zeros(0, np.int64)]
        self._taken.append((scan.t_mid_s, unique_keys(self._grid.keys(
            scan.points[np.concatenate(taken)]))))
        del self._taken[:-_TAKEN_SCANS]
        # two tracks updated in this scan within merge_m of each other follow one object (a
        # box's faces seen through different windows, born apart): the younger one ends
        now = [tr for tr in self.tracks.values() if tr.last_scan == scan.scan]
        for i, t1 in enumerate(now):
            for t2 in now[i + 1:]:
                if t1.track_id not in self.tracks or t2.track_id not in self.tracks:
                    continue
                if float(np.hypot(*(t1.x[:2] - t2.x[:2]))) <= cfg.coalesce_m and not (
                        cfg.coalesce_seen_apart
                        and min(len(t1.scans), len(t2.scans)) >= _KEPT_APART_SCANS
                        and t1.track_id in seen_idx and t2.track_id in seen_idx
                        and seen_apart(scan, seen_idx[t1.track_id], seen_idx[t2.track_id])):
                    young = t2 if len(t2.scans) < len(t1.scans) or (
                        len(t2.scans) == len(t1.scans) and t2.track_id > t1.track_id) else t1
                    del self.tracks[young.track_id]
                    self.ended.append(young)
                    changed.append(self._state(young, alive=False))
        # (clusters added after the shares, by following an unseen track, are their own)
        took = {ids[a]: {origin[b] if b < len(origin) else b for b in bs}
                for a, bs in members.items()}
        for tr in self._shared_ends(scan, shares, objs, now, took):
            changed.append(self._state(tr, alive=False))
        movers = np.concatenate([objs[b] for bs in members.values() for b in bs]
                                + [objs[b] for g in groups for b in g] + [np.zeros(0, np.int64)])
        for tid in list(self.tracks):
            tr = self.tracks[tid]
            if cfg.occluded_scans > 0 and tr.last_scan < scan.scan and len(movers) and \
                    self._hidden(tr, scan, movers):
                tr.hidden += 1
            if cfg.reacquire_gone_only and len(tr.scans) == 1 and tr.last_scan < scan.scan:
                self._look_at_place(tr, scan)
            if scan.scan - tr.last_scan > cfg.max_missed + min(tr.hidden, cfg.occluded_scans):
                del self.tracks[tid]
                self.ended.append(tr)
                changed.append(self._state(tr, alive=False))
        return changed

    def _shared_ends(self, scan: ScanPoints, shares: list[list[tuple[int, int]]],
                     objs: list[np.ndarray], now: list[_Track],
                     took: dict[int, set[int]]) -> list[_Track]:
        """The younger of two tracks that split one cluster of this scan, unseen apart and
        moving alike, in ``shared_scans`` of their sightings in a row (ended here and
        returned); the count of every other pair seen this scan starts again. ``took``:
        per track updated here, the segmentation clusters it took; two tracks that took
        different ones were seen as two objects, and are never ended so."""
        cfg = self.config
        if cfg.shared_scans <= 0:
            return []
        ids_took = sorted(took)
        for i, t1 in enumerate(ids_took):
            for t2 in ids_took[i + 1:]:
                if not took[t1] & took[t2]:
                    self._apart.add((t1, t2))
        counted = set()
        for group in shares:
            for i, (t1, b1) in enumerate(group):
                for t2, b2 in group[i + 1:]:
                    if t1 not in self.tracks or t2 not in self.tracks or t1 == t2:
                        continue
                    m1, m2 = self.tracks[t1].motion, self.tracks[t2].motion
                    alike = m1 is not None and m2 is not None and float(np.hypot(
                        *(self.tracks[t1].x[2:] - self.tracks[t2].x[2:]))) <= cfg.shared_dv_m_s
                    key = (min(t1, t2), max(t1, t2))
                    n1, n2 = sorted((len(objs[b1]), len(objs[b2])))
                    # two halves of one object, not a coasting track's prediction taking
                    # a neighbour's edge (y-three: 4-7 points of a person's 50)
                    halves = n1 >= cfg.shared_fraction * n2
                    if alike and halves and key not in self._apart and \
                            not seen_apart(scan, objs[b1], objs[b2]):
                        self._shared[key] = self._shared.get(key, 0) + 1
                        counted.add(key)
        ids_now = {tr.track_id for tr in now}
        for key in list(self._shared):
            if key not in counted and (key[0] in ids_now or key[1] in ids_now
                                       or key[0] not in self.tracks or key[1] not in self.tracks):
                del self._shared[key]  # seen apart, or not sharing: in a row no more
        self._apart = {k for k in self._apart if k[0] in self.tracks and k[1] in self.tracks}
        ended = []
        for (t1, t2), n in list(self._shared.items()):
            if n < cfg.shared_scans or t1 not in self.tracks or t2 not in self.tracks:
                continue
            a, b = self.tracks[t1], self.tracks[t2]
            young = b if len(b.scans) < len(a.scans) or (
                len(b.scans) == len(a.scans) and b.track_id > a.track_id) else a
            self._reanchor(a if young is b else b, young)
            del self.tracks[young.track_id]
            del self._shared[(t1, t2)]
            self.ended.append(young)
            ended.append(young)
        return ended

    @staticmethod
    def _reanchor(keep: _Track, young: _Track) -> None:
        """Move ``keep``'s filtered position to the centroid of both tracks' latest parts
        (this scan's, of one object), its position variance grown by the shift: its own part
        was half the object, and the next scan's whole cluster lay 0.42 m from its
        prediction, beyond the gate (``track-edge-box-away``, lifted, seed 8: a new track
        on the box)."""
        if not keep.centroids or not young.centroids or keep.last_scan != young.last_scan:
            return
        nk, ny = len(keep.points[-1]), len(young.points[-1])
        c = (nk * np.asarray(keep.centroids[-1]) + ny * np.asarray(young.centroids[-1])) / (nk + ny)
        d = c - np.asarray(keep.centroids[-1])
        from stonesoup.types.state import GaussianState

        sv = np.array(keep.state.state_vector, float)
        P = np.array(keep.state.covar, float)
        sv[[0, 2], 0] += d
        P[np.ix_([0, 2], [0, 2])] += np.outer(d, d)
        keep.state = GaussianState(sv, P, timestamp=keep.state.timestamp)
        keep.centroids[-1] = c

    def _two_objects(self, scan: ScanPoints, a: np.ndarray, b: np.ndarray) -> bool:
        """Whether clusters ``a`` and ``b`` (beam indices) are surely two objects: seen
        apart, or on both sides of a nearer object that hides the gap between them and
        together wider than one object (``merge_hidden_extent_m``, as :meth:`_pieces`
        judges pieces: two people behind a third)."""
        if seen_apart(scan, a, b):
            return True
        if not hidden_between(scan, a, b):
            return False
        from scipy.spatial.distance import pdist

        return float(pdist(scan.points[np.concatenate([a, b]), :2]).max()) > \
            self.config.merge_hidden_extent_m

    def _pieces(self, scan: ScanPoints, a: np.ndarray, b: np.ndarray, dist_m: float) -> bool:
        """Whether clusters ``a`` and ``b`` (beam indices), centroids ``dist_m`` [m] apart,
        are pieces of one object: within ``merge_m`` and not seen apart, or within
        ``merge_hidden_m`` with the gap between them hidden by a nearer object."""
        cfg = self.config
        if dist_m <= cfg.merge_m and not (cfg.merge_seen_apart and seen_apart(scan, a, b)):
            return True
        if dist_m > cfg.merge_hidden_m or not hidden_between(scan, a, b):
            return False
        from scipy.spatial.distance import pdist

        # one object no wider than merge_hidden_extent_m: two people behind a third span more
        return float(pdist(scan.points[np.concatenate([a, b]), :2]).max()) <= \
            cfg.merge_hidden_extent_m

    def _path_keys(self, t_s: float) -> np.ndarray:
        """Voxel keys of the points tracks took ``static_age_s`` or more before ``t_s`` [s]
        (their path; ``TrackerConfig.follow_supported_m_s``: a supported cluster qualifies
        when at least half of its points lie in these voxels)."""
        old = [k for t, k in self._taken if t <= t_s - self._static_age_s]
        return unique_keys(np.concatenate(old)) if old else np.zeros(0, np.int64)

    def _add(self, tr: _Track, scan, idx, c, t) -> None:
        pts = scan.points[idx]
        if self.config.smooth_scan_beams > 0:
            pts = smooth_along_scan(pts, scan.ray_dir[idx], scan.range_m[idx], scan.steps[idx],
                                    scan.mirror[idx], self.config.smooth_scan_beams)
        tr.points.append(pts)
        tr.n_points += len(idx)
        tr.times.append(scan.t_s[idx])
        tr.mirrors.append(scan.mirror[idx])
        tr.weights.append(incidence_weights(pts, scan.ray_dir[idx], scan.steps[idx],
                                            scan.mirror[idx])
                          if self.config.incidence_weights and self.config.entropy == "renyi"
                          else None)
        tr.truth.append(None if scan.truth_id is None else scan.truth_id[idx])
        cfg = self.config
        tr.sigma.append(None if cfg.round_model == "off" else (
            np.broadcast_to(np.asarray(self._range_sigma(scan.range_m[idx]), float), idx.shape)
            if self._range_sigma is not None else np.full(len(idx), _ROUND_SIGMA_M)))
        edges = cut_edges(scan, idx, cfg.window_cut_reach_m, cfg.window_cut_occluders,
                          floor_z_m=self._floor_z_m if cfg.window_cut_floor else -np.inf)
        cut = np.isfinite(edges[:, 0, 0])
        # each line's bearing as its sine and cosine, once (_estimate takes them for every
        # scan of the window at each refinement); NaN where no line
        b = np.arctan2(edges[:, :, 3], edges[:, :, 2])
        tr.cut.append(np.stack([np.sin(b), np.cos(b)], axis=-1))
        tr.centroids_uncut.append(pts[~cut, :2].mean(axis=0) if np.count_nonzero(~cut) >= 3
                                  else np.full(2, np.nan))
        u = getattr(scan, "sensor_velocity_m_s", None)  # duck-typed scans may lack it
        tr.sensor_v.append(np.zeros(2) if u is None else np.asarray(u, float)[:2])
        lengths = np.zeros(0)
        if cfg.hold_sliding_lines and not tr.moved:
            from .segment import SegmentConfig

            sc = self._segment or SegmentConfig()
            ends = silhouette_ends(scan, idx, cfg.window_cut_reach_m,
                                   floor_z_m=sc.ground_z_m + sc.ground_clearance_m)
            both = ends[(ends >= 0).all(axis=1)]
            lengths = np.hypot(*(scan.points[both[:, 0], :2] - scan.points[both[:, 1], :2]).T)
        tr.outline_len.append(lengths)
        if cfg.window_cut_mask == "edges":
            edges = np.where(edges[:, :, 5:6] == 1, np.nan, edges)  # occluders' lines out
        tr.edges.append(edges if cfg.window_cut_mask != "off" else None)
        tr.v_before.append(tr.x[2:].copy() if tr.state is not None and tr.motion is not None
                           and len(tr.scans) - tr.start >= cfg.maneuver_scans
                           else np.full(2, np.nan))
        tr.scans.append(scan.scan)
        tr.centroids.append(np.asarray(c, float))
        tr.t_centroids.append(float(t))
        tr.last_scan = scan.scan
        tr.hidden = 0
        w = self.config.window_scans
        if not self.config.keep_points and len(tr.points) > w:
            # outside the refinement's window: emptied, not removed (lists stay aligned
            # with tr.scans and tr.centroids)
            for lst in (tr.points, tr.times, tr.mirrors, tr.truth, tr.weights, tr.sigma, tr.cut,
                        tr.edges):
                old = lst[-w - 1]
                lst[-w - 1] = None if old is None else old[:0]

    def states(self) -> list[TrackState]:
        """Current states of the live tracks."""
        return [self._state(tr) for tr in self.tracks.values()]

    def all_tracks(self) -> list[_Track]:
        """Live and ended internal tracks (for analysis: points, times, centroids)."""
        return list(self.tracks.values()) + self.ended
