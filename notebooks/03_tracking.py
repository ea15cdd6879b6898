# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 03 - Tracking a moving object with and without the mirrors (paper Sections V-VI)
#
# The paper's scenario in simulation: the sensor (URG-04LX with the four mirrors of
# `design/urg04lx-paper.toml`, nodding +-0.35 rad at 0.35 rad/s) on a robot, a cylinder
# (r 0.18 m, 1 m tall) 2 m ahead moving at 0.13 m/s, heading 89.4 deg. The same run twice:
# mirrors deployed, mirrors lifted.
#
# Pipeline (`nodlidar.tracking`): voxel map with free-space carving -> inconsistent
# voxels -> dynamic clusters -> coarse motion from centroids -> entropy refinement
# (eq. 11-13; the paper's voxel entropy and Rényi's quadratic entropy) -> tracks.
#
# "Converged" (not defined in the paper): the first scan, counted among the scans in which
# the object was detected, from which every later estimate stays within 0.01 m/s and 2 deg
# of the truth. Figures and the table go to `$NODLIDAR_OUT` (a temporary directory if
# unset). Run: `MPLBACKEND=Agg python notebooks/03_tracking.py`; the same study from the
# command line: `nodlidar study mirrors --out DIR`.

# %%
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from nodlidar.paper import PAPER_DESIGN
from nodlidar.solver import solve
from nodlidar.spec import load_design
from nodlidar.tracking import study
from nodlidar.tracking.segment import SegmentConfig, segment_batch
from nodlidar.tracking.simdata import simulate_scans

# the design file is package data: found from any working directory (Jupyter starts the
# kernel in notebooks/) and after a normal install, without __file__
OUT = Path(os.environ.get("NODLIDAR_OUT") or tempfile.mkdtemp(prefix="nodlidar-nb03-"))
OUT.mkdir(parents=True, exist_ok=True)
design = solve(load_design(PAPER_DESIGN))

# %% [markdown]
# ## Segmentation of one scan
#
# Dynamic points are the clusters holding inconsistent points (space a ray crossed in one
# scan and that returned a hit in another). Ground truth comes from the simulator.

# %%
scans = simulate_scans(design, 38, mirrors_deployed=True, seed=0)
segs = segment_batch(scans, SegmentConfig(), design.lidar.range_sigma_m)
s = segs[8]
truth = s.scan.truth_id >= 1
print(f"scan {s.scan.scan}: {int(s.scan.valid.sum())} returns, {int(truth.sum())} on the object, "
      f"{int(s.dynamic.sum())} segmented dynamic ({int((s.dynamic & truth).sum())} correct)")

fig = study.plot_segmentation(s)
fig.savefig(OUT / "segmentation_scan.png", dpi=100)

# %% [markdown]
# ## The raw cloud in 3D
#
# Every return of the 38 scans (world frame, the cylinder smeared along its path),
# coloured by the mirror the beam reflected off - a static view for users without
# Foxglove (`nodlidar view` streams the same live).

# %%
from nodlidar.analysis.plots import plot_cloud_3d  # noqa: E402

cloud_xyz = np.concatenate([sc.points[sc.valid] for sc in scans])
cloud_mirror = np.concatenate([sc.mirror[sc.valid] for sc in scans])
fig = plot_cloud_3d(cloud_xyz, mirror=cloud_mirror, title=f"{len(scans)} scans, mirrors deployed")
drawn = sum(len(c.get_offsets()) for c in fig.axes[0].collections)
print(f"{len(cloud_xyz)} points, {drawn} drawn; reflected: {int((cloud_mirror >= 0).sum())}")
assert 0 < drawn <= 30_000 and (cloud_mirror >= 0).any()
fig.savefig(OUT / "cloud_3d.png", dpi=100)

# %% [markdown]
# ## The study: mirrors deployed vs lifted
#
# 38 scans as in the paper (each run ~5 s here).

# %%
t0 = time.perf_counter()
res = study.run_study(design, n_scans=38, seed=0)
rows = study.study_table(res)
print(f"study: {time.perf_counter() - t0:.1f} s")
md = study.table_markdown(rows)
print(md)
(OUT / "study_mirrors.md").write_text(md + "\n")
(OUT / "study_mirrors.csv").write_text(study.table_csv(rows))

# %% [markdown]
# Paper: 13 of 38 scans saw the object, 28 traces with mirrors against 13 without;
# convergence from scan 7 with mirrors, 9 without. Here the nod ramp covers the 1 m
# cylinder in more scans (29 of 38), and with the mirrors each scan sees it through the
# direct window and two reflected windows (3 traces a scan): 39 traces against 13 in the
# first 13 scans, more than the paper's 28 (its mirrors did not all reach the object in
# every scan; ours do by construction of the scene).
#
# **Which entropy converges faster** (the issue asks; the paper uses eq. 12 only). Measured
# with `nodlidar study mirrors --seeds N --entropy renyi|voxel`, seed 0 and spread over
# seeds:
#
# | entropy | mirrors | no mirrors |
# |---|---|---|
# | Rényi, seed 0 | 5 | 14 |
# | Rényi, seeds 0-7 | 5-14, median 6.5 | 7-14, median 12 |
# | voxel (eq. 12), seed 0 | 25 | 26 |
# | voxel, seeds 0-5 | 15-27 | 15-27, or not at all (2 of 6: final heading 2.1 / 2.4 deg off) |
#
# Rényi's quadratic entropy converges several scans earlier and in every run; the paper's
# voxel occupancy entropy (with p = n/(n+1), which the paper leaves open) is piecewise
# constant in (v, heading) and, with a few hundred points spread over 3 cm voxels, its
# minimum wanders by a few degrees until most of the object's scans are in. Its final
# speed is within 0.01 m/s in every run, its final heading not always within 2 deg. We do
# not reproduce the paper's 7 vs 9 with either; with Rényi the mirrors converge earlier in
# 7 of 8 seeds (seed 7: 9 vs 7), which is the paper's qualitative claim.

# %%
mir, nom = res.configs
print(f"traces: mirrors {mir.traces_total}, no mirrors {nom.traces_total} in {mir.scans_seen} scans")
print(f"points per scan on the object: mirrors {mir.points_total / mir.scans_seen:.1f}, "
      f"no mirrors {nom.points_total / nom.scans_seen:.1f}")
for ent in ("renyi", "voxel"):
    print(f"{ent:6s} convergence (v, heading, both): mirrors {mir.convergence[ent]}, "
          f"no mirrors {nom.convergence[ent]}")
assert abs(mir.estimates["renyi"]["v"][-1] - 0.13) <= 0.01
assert abs(mir.estimates["renyi"]["heading_deg"][-1] - 89.4) <= 2.0

# %% [markdown]
# ## Figures 10-13: accumulated motion-compensated cloud, convergence

# %%
study.plot_clouds(res).savefig(OUT / "fig10_12_accumulated_clouds.png", dpi=100)
study.plot_convergence(res).savefig(OUT / "fig13_convergence.png", dpi=100)
print(f"figures in {OUT}")
print("final errors:", {c.label: {k: {q: round(x, 4) for q, x in e.items()}
                                  for k, e in c.final_error.items()} for c in res.configs})
assert np.isfinite(mir.estimates["renyi"]["v"][-1])
