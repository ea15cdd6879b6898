"""Lidar models against the SCIP reference (tests/data/scip2.md, a copy of the shared reference)."""

import re
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from nodlidar.errors import ParameterError
from nodlidar.lidar import LIDAR_MODELS, lidar_model

SCIP_MD = Path(__file__).resolve().parent / "data" / "scip2.md"


def _pp_block():
    """The URG-04LX PP example of the reference, parsed (KEY -> value string)."""
    assert SCIP_MD.exists(), f"{SCIP_MD} (the SCIP 2.0 reference) is missing"
    text = SCIP_MD.read_text()
    block = text[text.index("```\nPP\n00P"):]
    block = block[: block.index("(empty line)")]
    return dict(re.findall(r"^([A-Z]{4}):([^;]*);", block, re.M))


def test_urg04lx_matches_the_pp_reply_in_the_reference():
    pp = _pp_block()
    m = lidar_model("URG-04LX")
    assert (m.steps_per_rev, m.step_min, m.step_max, m.step_front) == (
        int(pp["ARES"]), int(pp["AMIN"]), int(pp["AMAX"]), int(pp["AFRT"]))
    assert m.rpm == float(pp["SCAN"])
    assert_allclose([m.range_min_m, m.range_max_m], [int(pp["DMIN"]) / 1e3, int(pp["DMAX"]) / 1e3])


def test_urg04lx_step_geometry():
    m = lidar_model("urg-04lx")  # case-insensitive
    assert m.n_steps == 682
    # scip2.md §1.5: AMIN 44 -> -119.53 deg, AFRT 384 -> 0, AMAX 725 -> +119.88 deg (printed to 0.01)
    assert_allclose(np.degrees(m.bearing_from_step([44, 384, 725])), [-119.53, 0.0, 119.88], atol=0.005)
    assert_allclose(np.degrees(m.angular_resolution), 0.3515625, rtol=0, atol=1e-12)
    # 600 rpm -> 100 ms a scan -> 97.65625 us a step (hokuyoaist's printed figure)
    assert_allclose(m.step_period_s, 97.65625e-6, rtol=1e-12)
    assert_allclose(m.time_offset_from_step([44, 725]), [0.0, 681 * 97.65625e-6], rtol=1e-12)
    assert_allclose(m.step_from_bearing(m.bearing_from_step(m.steps)), m.steps, atol=1e-9)


@pytest.mark.parametrize("name", ["UTM-30LX", "UST-10LX"])
def test_270_degree_models(name):
    m = LIDAR_MODELS[name]
    assert_allclose(np.degrees(m.bearing_from_step([m.step_min, m.step_max])), [-135, 135])
    assert_allclose(m.scan_period_s, 0.025)


def test_unknown_model_names_the_allowed_ones():
    with pytest.raises(ParameterError, match="URG-04LX, UTM-30LX, UST-10LX"):
        lidar_model("LMS111")


def test_noise_model_follows_the_spec():
    m = lidar_model("URG-04LX")
    assert_allclose(m.range_sigma_m([0.5, 1.0, 4.0]), [0.01, 0.01, 0.04])


def test_beam_time_refers_to_step_zero():
    # SCIP stamps a scan at step 0: a beam is step * 60/(rpm*ARES) later, written out here
    # from the URG-04LX's PP figures (600 rpm, ARES 1024: 0.1 s / 1024 a step); the older
    # helpers are differences of beam_time_s and must say the same. 1e-15 s: a few ulp of 2 s.
    from nodlidar.lidar import lidar_model

    m = lidar_model("URG-04LX")
    steps = np.array([m.step_min, m.step_front, m.step_max])
    np.testing.assert_allclose(m.beam_time_s(2.0, steps), 2.0 + steps * 0.1 / 1024, rtol=0, atol=1e-15)
    np.testing.assert_allclose(m.first_step_offset_s, 44 * 0.1 / 1024, rtol=1e-15)
    # a difference of two times <= 0.07 s: a few ulp of 0.07 s (1.4e-17 s each)
    np.testing.assert_allclose(m.time_offset_from_step(steps), (steps - 44) * 0.1 / 1024,
                               rtol=0, atol=5e-17)
