"""The in-process pipeline on a geometric radio profile: the corner, DCC and CPM rules end to end."""

from __future__ import annotations

import pytest

from mapcontainer.experiments.network_radio import gap_scenario, radio_figures
from mapcontainer.pipeline import run_pipeline

pytestmark = [pytest.mark.integration, pytest.mark.slow]  # three short runs: about 20 s on a loaded machine


def test_round_the_corner_the_link_is_nlos_and_the_classic_profiles_are_unchanged():
    near = run_pipeline(gap_scenario(12.0), seed=1, duration_s=1.5, network="its-g5", start="warm", cpm_rules=True)
    far = run_pipeline(gap_scenario(150.0), seed=1, duration_s=1.5, network="its-g5", start="warm")
    fn, ff = radio_figures(near), radio_figures(far)
    assert fn["state_nlos_fraction"] == 0 and ff["state_nlos_fraction"] > 0.5
    assert near.channel_stats["delivered_msgs"] >= 14 and ff["drop_sensing_fraction"] > 0.5
    assert 0 < fn["cbr_mean"] < 0.2
    classic = run_pipeline(gap_scenario(150.0), seed=1, duration_s=1.5, network="dsrc", start="warm")
    assert "radio_drops" not in classic.channel_stats and classic.channel_stats["delivered_msgs"] > 0
