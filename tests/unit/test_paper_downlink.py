"""The paper experiment with the downlink on and off (mapcontainer.experiments.paper.onoff): the runs with the
downlink borrow their twin's centralized reference, the tasks come in twins, the figures of both settings are
side by side from the same seeds, whatever order the runs finished in, and the CLI's ``--downlink`` choices."""

from __future__ import annotations

import pytest

from mapcontainer import jsonout
from mapcontainer.cli import build_parser
from mapcontainer.experiments.paper import PaperSettings, aggregate
from mapcontainer.experiments.paper.onoff import borrow_reference, section, split_by_downlink
from mapcontainer.experiments.paper.report import report, runs_csv
from mapcontainer.experiments.paper.runs import tasks

SETTINGS = PaperSettings(runs=2, seed=5, scenarios=("urban",), sensitivity_runs=0, duration_s=4.0, burnin_s=1.0,
                         downlink_compare=True)  # fmt: skip


def _run(seed: int, downlink: bool, onboard_sq: float, reference: bool) -> dict:
    """A simulation run of two vehicles: on-board squared errors ``onboard_sq`` in its scored frames, fused 0.04 m^2;
    ``reference``: with the centralized reference (0.01 m^2)."""
    series = {
        f"{v}:{m}": [[t, sq] for t in (1.0, 2.0)]
        for v in ("cv0", "cv1")
        for m, sq in (("onboard", onboard_sq), ("cooperative", 0.04), ("gnss", 4.0), ("map_matching", 0.25))
    }
    series.update({"objects:cooperative": [[1.0, 0.09]], "targets:cooperative": [[1.0, 0.16]]})
    nees = {f"{v}:onboard_xy": [[t, 1, 2.0 * onboard_sq / 0.09] for t in (1.0, 2.0)] for v in ("cv0", "cv1")}
    objects = {"objects:cooperative": [[1.0, 2, 2, 2, 0.2, 0.2, 0.0, 0.0]]}
    extra = {}
    if reference:
        for v in ("cv0", "cv1"):
            series[f"{v}:centralized"] = [[1.0, 0.01], [2.0, 0.01]]
            nees[f"{v}:centralized"] = [[1.0, 1, 6.0]]
        series["objects:centralized"] = [[1.0, 0.0729]]
        objects["objects:centralized"] = [[1.0, 2, 2, 2, 0.1, 0.1, 0.0, 0.0]]
        extra = {"tx_bytes_centralized": 40_000, "tx_msgs_centralized": 80}
    return {
        "kind": "sim",
        "key": "urban",
        "scenario": "urban",
        "variant": "all",
        "seed": seed,
        "downlink": downlink,
        "vehicles": ["cv0", "cv1"],
        "series": series,
        "nees": nees,
        "objects": objects,
        "locks": [[t, i, 1, 0.1] for t in (0.0, 1.0, 2.0, 3.0) for i in (0, 1)],
        "tx_bytes": 8000,
        "tx_msgs": 80,
        "rx_bytes": 4000 if downlink else 0,
        "rx_msgs": 40 if downlink else 0,
        "downlink_frames": {"fused": 70, "refused": 10} if downlink else {},
        **extra,
    }


def _runs() -> list[dict]:
    """Two seeds, each without the downlink (with the reference) and with it (on board 0.3 m -> 0.2 m)."""
    return [_run(seed, on, 0.04 if on else 0.09, reference=not on) for seed in (5, 6) for on in (False, True)]


def test_a_run_with_the_downlink_borrows_the_reference_of_its_twin_and_only_it() -> None:
    off = [_run(5, False, 0.09, True), _run(6, False, 0.09, True)]
    on = [_run(6, True, 0.04, False), _run(7, True, 0.04, False)]  # seed 7 has no twin
    got = borrow_reference(on, off)
    assert got[0]["series"]["cv1:centralized"] == off[1]["series"]["cv1:centralized"]
    assert got[0]["objects"]["objects:centralized"] == off[1]["objects"]["objects:centralized"]
    assert (
        got[0]["tx_bytes_centralized"] == 40_000 and got[0]["series"]["cv0:onboard"] == on[0]["series"]["cv0:onboard"]
    )
    assert "tx_msgs_centralized" not in got[1] and "cv0:centralized" not in got[1]["series"]
    assert "cv0:centralized" not in on[0]["series"]  # the runs themselves are left as they were
    main, other = split_by_downlink([*off, *on], downlink=False)
    assert [r["downlink"] for r in main] == [False, False] and [r["seed"] for r in other] == [6, 7]


def test_the_tasks_come_in_twins_with_the_same_seed() -> None:
    once = tasks(PaperSettings(runs=2, seed=5, scenarios=("urban",), sensitivity_runs=0))
    twice = tasks(SETTINGS)
    assert len(twice) == 2 * len(once)
    for a, b in zip(twice[::2], twice[1::2], strict=True):
        assert a[:5] == b[:5] and (a[5]["downlink"], b[5]["downlink"]) == (False, True)
        assert a[5]["downlink_compare"] and b[5]["downlink_compare"]


def test_the_on_off_figures_are_from_the_same_seeds_and_do_not_depend_on_the_runs_order() -> None:
    runs = _runs()
    res = aggregate(runs, SETTINGS)
    c = res["downlink_on_off"]
    assert c["seeds"] == [5, 6] and c["report_setting"] == "off"
    off, on = c["simulation"]["urban"]["off"], c["simulation"]["urban"]["on"]
    assert (off["vehicles_onboard_rmse_m"], on["vehicles_onboard_rmse_m"]) == pytest.approx((0.3, 0.2))
    assert off["vehicles_fused_rmse_m"] == on["vehicles_fused_rmse_m"] == pytest.approx(0.2)
    assert (off["onboard_anees_2dof"], on["onboard_anees_2dof"]) == (2.0, 0.8889)  # rounded as results.json keeps them
    # bytes per second over the fleet: 8000 bytes up in each 4 s run, 4000 down with the downlink
    assert (off["up_bytes_per_s"], off["down_bytes_per_s"], on["down_bytes_per_s"]) == (2000.0, 0.0, 1000.0)
    # the same reference for both: centralized 0.1 m against fused 0.2 m; bytes 40000 / (8000 + 4000)
    assert off["efficiency_vehicles"] == on["efficiency_vehicles"] == pytest.approx(0.25)
    assert (off["centralized_over_distributed_bytes"], on["centralized_over_distributed_bytes"]) == (5.0, 3.33)
    assert on["downlink_frames"] == {"fused": 140, "refused": 20} and off["downlink_frames"] == {}
    assert res["downlink_other"]["simulation"]["urban"]["vehicles_rmse_m"]["onboard"] == pytest.approx(0.2)
    assert res["simulation"]["urban"]["vehicles_rmse_m"]["onboard"] == pytest.approx(0.3)  # the report's: off
    assert jsonout.dumps(aggregate(runs[::-1], SETTINGS)) == jsonout.dumps(res)  # any order of finishing

    text = report(res)
    assert "`mapc experiment paper --runs 2 --seed 5 --scenario urban --downlink both`" in text
    rows = [line for line in section(res) if line.startswith("| urban |")]
    assert [r.split(" | ")[1] for r in rows] == ["off", "on", "off", "on"]
    assert rows[0].split(" | ")[2:4] == ["0.300", "0.300"] and rows[1].split(" | ")[2:4] == ["0.200", "0.200"]
    assert "| 2000 | 0 |" in rows[2] and "| 2000 | 1000 |" in rows[3] and "fused 140, refused 20" in rows[3]
    assert text.index("## The downlink on and off") < text.index("## Targets")
    csv = runs_csv(runs, 1.0, downlink_column=True).splitlines()
    assert csv[0].startswith("kind,key,variant,seed,downlink,") and [x.split(",")[4] for x in csv[1:]] == [
        "off",
        "on",
        "off",
        "on",
    ]


def test_without_the_comparison_nothing_changes() -> None:
    runs = [r for r in _runs() if not r["downlink"]]
    s = PaperSettings(runs=2, seed=5, scenarios=("urban",), sensitivity_runs=0, duration_s=4.0, burnin_s=1.0)
    res = aggregate(runs, s)
    assert "downlink_on_off" not in res and "downlink_other" not in res and section(res) == []
    assert "--downlink" not in report(res).splitlines()[2]
    assert runs_csv(runs, 1.0).splitlines()[0].startswith("kind,key,variant,seed,cv0:")


@pytest.mark.parametrize(
    ("flag", "on", "both"), [((), False, False), (("--downlink",), True, False), (("--downlink", "both"), False, True)]
)
def test_the_cli_downlink_choices(flag, on, both, monkeypatch, tmp_path) -> None:
    from mapcontainer import cli

    seen = {}

    def fake(out, settings, executor, progress, fresh):
        seen["settings"] = settings
        return {"targets": [], "wall_s": 0.0, "resumed": 0, "runs": settings.runs}

    monkeypatch.setattr("mapcontainer.experiments.paper.run_paper_experiment", fake)
    args = build_parser().parse_args(
        ["experiment", "paper", "--runs", "1", "--seed", "3", "--out", str(tmp_path), *flag]
    )
    assert cli._cmd_experiment_paper(args) == 0
    assert (seen["settings"].downlink, seen["settings"].downlink_compare) == (on, both)
