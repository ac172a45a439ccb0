"""calibrate(): every (θ, gate, γ) combination is scored on the same scenes with its own settings."""
import json
from pathlib import Path

import numpy as np
import pytest

import fpcc_ros.pipeline as pipeline_module
from fpcc_ros.calibrate import calibrate
from fpcc_ros.onnx_model import FpccModel

from test_evaluation import FLOOR, patch, write_scene

TINY_MODEL = Path(__file__).resolve().parent / "data" / "tiny_fpcc.onnx"
TINY_CARD_VOXEL = json.loads(TINY_MODEL.with_suffix(".json").read_text())["voxel_factor"]
# three parts of 21 x 21 points: above the visible protocol's 300-point floor for unorganized scenes
ROW = [patch(0.0, 0.05, 0.98, step=0.0025, size=0.05), patch(0.065, 0.05, 0.97, step=0.0025, size=0.05),
       patch(0.13, 0.05, 0.985, step=0.0025, size=0.05)]


def test_every_combination_is_scored_on_all_scenes_with_its_own_settings(tmp_path, monkeypatch):
    scenes = [tmp_path / "a.npz", tmp_path / "b.npz"]
    for path in scenes:
        write_scene(path, ROW, extra=FLOOR, part_radius=0.05)
    seen: list[tuple[float, float]] = []  # (score threshold, screening radius) per NMS call
    real_nms = pipeline_module.nms_centers

    def recording_nms(xyz, score, threshold, radius):
        seen.append((threshold, round(radius, 6)))  # part_radius is stored as float32
        return real_nms(xyz, score, threshold, radius)

    monkeypatch.setattr(pipeline_module, "nms_centers", recording_nms)
    rows = calibrate(FpccModel(TINY_MODEL, threads=1), scenes, [0.3, 0.999], [1.0], merges=[0.0],
                     screening_factors=[0.5, 1.0])

    assert sorted((r.score_threshold, r.screening_factor) for r in rows) == \
        [(0.3, 0.5), (0.3, 1.0), (0.999, 0.5), (0.999, 1.0)]
    # each combination ran once per scene with its own θ and γ * part_radius
    assert sorted(set(seen)) == [(0.3, 0.025), (0.3, 0.05), (0.999, 0.025), (0.999, 0.05)]
    assert len(seen) == 4 * len(scenes)
    # the same scenes under every setting: three ground-truth parts per scene
    assert all(r.counts.ground_truths == 3 * len(scenes) for r in rows)
    assert all(0.0 <= r.f1 <= 1.0 for r in rows)


def test_without_screening_factors_the_cards_factor_is_kept(tmp_path):
    scene = tmp_path / "a.npz"
    write_scene(scene, ROW, extra=FLOOR, part_radius=0.05)
    model = FpccModel(TINY_MODEL, threads=1)
    rows = calibrate(model, [scene], [0.5], [1.0, 2.0])
    assert [r.screening_factor for r in rows] == [model.card.screening_factor] * 2
    assert sorted(r.feature_gate for r in rows) == [1.0, 2.0]


def test_cli_writes_the_best_combination_into_the_card(tmp_path, capsys):
    import json
    import shutil

    from fpcc_ros.cli import main as fpcc

    for suffix in (".onnx", ".json"):
        shutil.copy(TINY_MODEL.with_suffix(suffix), tmp_path / f"m{suffix}")
    (tmp_path / "val").mkdir()
    (tmp_path / "empty").mkdir()
    write_scene(tmp_path / "val" / "a.npz", ROW, extra=FLOOR, part_radius=0.05)
    assert fpcc(["calibrate", str(tmp_path / "m.onnx"), "--data", str(tmp_path / "val"),
                 "--thresholds", "0.2", "0.4", "--gates", "1.5", "--screening", "0.7",
                 "--merges", "0.25", "--prototypes", "0.4", "--voxel-factors", "0.12",
                 "--write"]) == 0
    card = json.loads((tmp_path / "m.json").read_text())
    chosen = card["metrics"]["calibration"]
    assert card["score_threshold"] == chosen["score_threshold"] in (0.2, 0.4)
    assert (card["feature_gate"], card["screening_factor"], card["center_merge"],
            card["center_prototype"], card["voxel_factor"]) == (1.5, 0.7, 0.25, 0.4, 0.12)
    assert chosen["voxel_factor"] == 0.12
    assert chosen["objective"] == "part-mean" and chosen["parts"] == 1
    assert f"pooled F1 {chosen['f1']:.3f}, mean part F1 {chosen['f1']:.3f}; 1 scenes" in \
        capsys.readouterr().out

    assert fpcc(["calibrate", str(tmp_path / "m.onnx"), "--data", str(tmp_path / "val"),
                 "--voxel-factors", "0.1", "0"]) == 2
    assert "every value must be > 0" in capsys.readouterr().err
    assert fpcc(["calibrate", str(tmp_path / "missing.onnx"), "--data", str(tmp_path / "val")]) == 2
    assert "missing.onnx" in capsys.readouterr().err
    assert fpcc(["calibrate", str(tmp_path / "m.onnx"), "--data", str(tmp_path / "nothing")]) == 2
    assert "nothing: no such file or folder" in capsys.readouterr().err
    assert fpcc(["calibrate", str(tmp_path / "m.onnx"), "--data", str(tmp_path / "empty")]) == 2
    assert "fpcc synth" in capsys.readouterr().err


def test_reused_block_inputs_give_the_plain_pipelines_counts(tmp_path):
    """calibrate() reuses each scene's network outputs and block inputs across settings; the
    counts must be those of a fresh Pipeline per setting."""
    from fpcc_ros.metrics import scene_counts
    from fpcc_ros.pipeline import Pipeline, PipelineConfig

    scenes, names = [], ["nut", "nut", "shaft"]
    for i, parts in enumerate((ROW, ROW[1:], [ROW[0] + [0, 0, 0.01], ROW[2]])):
        scenes.append(tmp_path / f"s{i}.npz")
        write_scene(scenes[-1], parts, extra=FLOOR, part_radius=0.05, part_name=names[i])
    model = FpccModel(TINY_MODEL, threads=1)
    rows = calibrate(model, scenes, [0.2, 0.5], [1.0, 3.0], screening_factors=[0.5],
                     merges=[0.0, 1.0], prototypes=[0.0, 0.6], voxel_factors=[0.05, 0.1])
    assert len(rows) == 32 and {r.voxel_factor for r in rows} == {0.05, 0.1}
    for row in rows:
        want, by_part = None, {}
        for path, name in zip(scenes, names):
            scene = np.load(path)
            cfg = PipelineConfig.from_card(model.card, part_radius=float(scene["part_radius"]),
                                           score_threshold=row.score_threshold,
                                           feature_gate=row.feature_gate, screening_factor=0.5,
                                           center_merge=row.center_merge,
                                           center_prototype=row.center_prototype,
                                           voxel_factor=row.voxel_factor)
            labels = Pipeline(model, cfg).segment(scene["points"]).labels
            counts = scene_counts(labels, scene["instance"], "visible", 300)
            want = counts if want is None else want + counts
            by_part[name] = by_part[name] + counts if name in by_part else counts
        assert row.part_counts == by_part
        assert row.counts == want, (row.score_threshold, row.feature_gate, row.center_merge,
                                    row.center_prototype, row.voxel_factor)
    # the voxel size matters here (else the sweep over it proves nothing)
    by_voxel = {v: sum((r.counts for r in rows if r.voxel_factor == v
                        and r.score_threshold == 0.2), start=type(rows[0].counts)())
                for v in (0.05, 0.1)}
    assert by_voxel[0.05] != by_voxel[0.1]


def test_part_mean_objective_counts_every_part_once():
    """Hand-computed: a part with many instances dominates the pooled F1, not the part mean."""
    from fpcc_ros.calibrate import CalibrationRow
    from fpcc_ros.metrics import InstanceCounts

    nuts = InstanceCounts(true_positives=8, predictions=10, ground_truths=10)    # F1 0.8
    shafts = InstanceCounts(true_positives=1, predictions=2, ground_truths=4)    # F1 1/3
    row = CalibrationRow(0.5, 1.0, nuts + shafts, part_counts={"nut": nuts, "shaft": shafts})
    assert abs(row.part_mean_f1 - (0.8 + 1 / 3) / 2) < 1e-12
    # pooled: P 9/12, R 9/14
    assert abs(row.f1 - 2 * (9 / 12) * (9 / 14) / (9 / 12 + 9 / 14)) < 1e-12
    assert row.score("part-mean") == row.part_mean_f1 and row.score("pooled") == row.f1
    # a setting better for the shafts, worse for the nuts, wins only on the part mean
    fair = CalibrationRow(0.5, 1.0, InstanceCounts(6, 10, 10) + InstanceCounts(3, 4, 4),
                          part_counts={"nut": InstanceCounts(6, 10, 10),
                                       "shaft": InstanceCounts(3, 4, 4)})
    assert fair.score("part-mean") > row.score("part-mean")
    assert fair.score("pooled") < row.score("pooled")
    # scenes without part names: one group, the pooled F1
    assert CalibrationRow(0.5, 1.0, nuts).part_mean_f1 == CalibrationRow(0.5, 1.0, nuts).f1


def test_settings_on_the_edge_of_the_grid_are_reported():
    """The best θ is the largest tried and its gate the smallest: both are named with the option
    to widen; a middle value, a single value and merge/prototype 0 (off) are not."""
    import itertools

    from fpcc_ros.calibrate import CalibrationRow, settings_on_grid_edge
    from fpcc_ros.metrics import InstanceCounts

    rows = [CalibrationRow(t, g, InstanceCounts(1, 2, 2), screening_factor=f, center_merge=m,
                           center_prototype=0.0)
            for t, g, f, m in itertools.product([0.5, 0.7], [0.75, 1.0], [0.5, 0.7, 0.8],
                                                [0.0, 0.5])]
    best = next(r for r in rows if (r.score_threshold, r.feature_gate, r.screening_factor,
                                    r.center_merge) == (0.7, 0.75, 0.7, 0.0))
    assert settings_on_grid_edge(rows, best) == [
        ("score_threshold", "--thresholds", 0.7, "largest"),
        ("feature_gate", "--gates", 0.75, "smallest")]
    inner = next(r for r in rows if (r.score_threshold, r.feature_gate, r.screening_factor,
                                     r.center_merge) == (0.5, 1.0, 0.8, 0.5))
    assert settings_on_grid_edge(rows, inner) == [
        ("score_threshold", "--thresholds", 0.5, "smallest"),
        ("feature_gate", "--gates", 1.0, "largest"),
        ("screening_factor", "--screening", 0.8, "largest"),
        ("center_merge", "--merges", 0.5, "largest")]


def test_cli_says_when_the_best_setting_is_on_the_grids_edge(tmp_path, capsys):
    import shutil

    from fpcc_ros.cli import main as fpcc

    for suffix in (".onnx", ".json"):
        shutil.copy(TINY_MODEL.with_suffix(suffix), tmp_path / f"m{suffix}")
    (tmp_path / "val").mkdir()
    write_scene(tmp_path / "val" / "a.npz", ROW, extra=FLOOR, part_radius=0.05)
    # one value per setting but the gates: whichever gate wins is on an edge
    assert fpcc(["calibrate", str(tmp_path / "m.onnx"), "--data", str(tmp_path / "val"),
                 "--thresholds", "0.4", "--gates", "0.5", "3.0", "--screening", "0.7",
                 "--merges", "0", "--prototypes", "0"]) == 0
    out = capsys.readouterr().out
    assert "run again with more values in --gates" in out
    assert "--thresholds" not in out.split("best (")[1]


@pytest.fixture
def table_of_one_setting(tmp_path, capsys):
    """Runs `fpcc calibrate` on a copy of the tiny model with one network setting (θ, gate, γ,
    merge, prototype) and the extra options given; returns the printed table's rows, split."""
    import shutil

    from fpcc_ros.cli import main as fpcc

    for suffix in (".onnx", ".json"):
        shutil.copy(TINY_MODEL.with_suffix(suffix), tmp_path / f"m{suffix}")
    (tmp_path / "val").mkdir()
    write_scene(tmp_path / "val" / "a.npz", ROW, extra=FLOOR, part_radius=0.05)
    one_setting = ["--thresholds", "0.4", "--gates", "1.0", "--screening", "0.7", "--merges",
                   "0", "--prototypes", "0"]

    def run(*extra: str) -> list[list[str]]:
        assert fpcc(["calibrate", str(tmp_path / "m.onnx"), "--data", str(tmp_path / "val"),
                     *one_setting, *extra]) == 0
        table = capsys.readouterr().out.split("best (")[0].splitlines()[1:]
        return [line.split() for line in table if line.strip()]
    return run


def test_cli_tries_both_clusterings_unless_told(table_of_one_setting):
    """A freshly exported card says clustering "paper"; calibrating that mode alone left the
    connected clustering (0.619 against 0.535 test F1 for a gear-shaft fine-tune) untried."""
    assert {row[6] for row in table_of_one_setting()} == {"paper", "connected"}
    assert {row[6] for row in table_of_one_setting("--clusterings", "paper")} == {"paper"}


# The row each refine pass starts from in the tests below: every setting away from its default,
# so a setting the pass failed to copy shows.
REFINED_FROM = dict(score_threshold=0.5, feature_gate=0.75, screening_factor=0.7,
                    center_merge=0.5, center_prototype=0.3, voxel_factor=0.1,
                    clustering="connected", fragment_eps=0.004, fragment_density=5,
                    fragment_join=1.2, fragment_crease=60.0)


def _row_at(hits: int, **changes):
    """A grid row at :data:`REFINED_FROM` but ``changes``, with ``hits`` of 10 parts found."""
    from fpcc_ros.calibrate import CalibrationRow
    from fpcc_ros.metrics import InstanceCounts

    settings = {**REFINED_FROM, **changes}
    return CalibrationRow(settings.pop("score_threshold"), settings.pop("feature_gate"),
                          InstanceCounts(hits, 10, 10), **settings)


def _assert_refined_from(rows, best, changed: str) -> None:
    """Each of a refine pass's ``rows`` has every swept setting of ``best`` but ``changed`` and
    was scored on the one three-part scene (its counts were not copied from ``best``)."""
    from fpcc_ros.calibrate import SWEPT_SETTINGS

    expected = {name: getattr(best, name) for name, _ in SWEPT_SETTINGS if name != changed}
    for r in rows:
        assert {name: getattr(r, name) for name in expected} == expected
        assert r.counts.ground_truths == 3


@pytest.fixture
def scene_and_model(tmp_path):
    """The one three-part scene the refine passes score, and the tiny model."""
    scene = tmp_path / "a.npz"
    write_scene(scene, ROW, extra=FLOOR, part_radius=0.05)
    return scene, FpccModel(TINY_MODEL, threads=1)


@pytest.mark.parametrize("refine, changed, values, tried, expected", [
    ("refine_fragment_eps", "fragment_eps", {"eps_values": (0.004, 0.006, 0.02)}, 0.006,
     [0.004, 0.02]),
    ("refine_fragment_join", "fragment_join", {"joins": (1.2, 2.0, 3.0)}, 2.0, [1.2, 3.0]),
])
def test_refine_sweeps_one_setting_at_the_best_connected_settings(scene_and_model, refine, changed,
                                                                  values, tried, expected):
    """The radius and join passes copy every setting of the best *connected* row (not the best
    row overall, here a paper one) and change only their own setting, skipping the one tried."""
    import fpcc_ros.calibrate as calibrate
    from fpcc_ros.calibrate import CalibrationRow
    from fpcc_ros.metrics import InstanceCounts

    refine_pass = getattr(calibrate, refine)
    scene, model = scene_and_model
    best = _row_at(7, feature_gate=1.0, voxel_factor=0.08, **{changed: tried})
    grid = [CalibrationRow(0.3, 1.0, InstanceCounts(9, 10, 10), clustering="paper"),
            CalibrationRow(0.3, 1.0, InstanceCounts(4, 10, 10), screening_factor=0.5,
                           clustering="connected"),
            best,
            CalibrationRow(0.4, 1.0, InstanceCounts(6, 10, 10), clustering="connected",
                           fragment_join=3.0)]
    rows = refine_pass(model, [scene], grid, "part-mean", **values)
    assert rows[:4] == grid
    added = rows[4:]
    assert sorted(getattr(r, changed) for r in added) == expected
    _assert_refined_from(added, best, changed)
    # nothing connected: nothing to refine
    assert refine_pass(model, [scene], grid[:1], "part-mean") == grid[:1]


def test_cli_refines_the_fragment_join_unless_joins_are_given(table_of_one_setting):
    from fpcc_ros.calibrate import REFINE_FRAGMENT_JOINS

    def joins_tried(*extra: str) -> set[float]:
        return {float(row[10]) for row in table_of_one_setting(*extra) if row[6] == "connected"}

    assert joins_tried() == set(REFINE_FRAGMENT_JOINS)   # the card's 2 among them
    assert joins_tried("--fragment-joins", "1.5") == {1.5}
    assert joins_tried("--clusterings", "paper") == set()


def test_refine_sweeps_voxel_factors_at_the_best_settings(scene_and_model):
    """The voxel pass copies every setting of the best row, whichever its clustering, changes
    only the voxel factor (skipping the one tried) and scores each on the scenes."""
    from fpcc_ros.calibrate import CalibrationRow, refine_voxel_factor
    from fpcc_ros.metrics import InstanceCounts

    scene, model = scene_and_model
    best = _row_at(8)
    grid = [CalibrationRow(0.3, 1.0, InstanceCounts(4, 10, 10), clustering="paper"), best]
    rows = refine_voxel_factor(model, [scene], grid, "part-mean", factors=(0.1, 0.07, 0.06))
    assert rows[:2] == grid
    added = rows[2:]
    assert sorted(r.voxel_factor for r in added) == [0.06, 0.07]
    _assert_refined_from(added, best, "voxel_factor")
    # only the factor already tried: nothing to add
    assert refine_voxel_factor(model, [scene], grid, "part-mean", factors=(0.1,)) == grid


def test_cli_refines_the_voxel_factor_unless_factors_are_given(table_of_one_setting):
    from fpcc_ros.calibrate import REFINE_VOXEL_FACTORS

    def factors_tried(*extra: str) -> set[float]:
        return {float(row[5]) for row in table_of_one_setting(*extra)}

    assert factors_tried() == set(REFINE_VOXEL_FACTORS) | {TINY_CARD_VOXEL}
    assert factors_tried("--voxel-factors", "0.12") == {0.12}


def test_cli_refines_the_fragment_radius_unless_radii_are_given(table_of_one_setting):
    from fpcc_ros.calibrate import REFINE_FRAGMENT_EPS
    card_join = FpccModel(TINY_MODEL, threads=1).card.fragment_join

    def radii_tried(*extra: str) -> list[float]:
        # at the card's voxel and join: their passes add rows at the best radius only
        return sorted(float(row[7]) for row in table_of_one_setting(*extra)
                      if row[6] == "connected" and float(row[5]) == TINY_CARD_VOXEL
                      and float(row[10]) == card_join)

    assert radii_tried() == [e * 1e3 for e in REFINE_FRAGMENT_EPS]   # the card's 6 mm among them
    assert radii_tried("--fragment-eps", "0.008") == [8.0]
    assert radii_tried("--clusterings", "paper") == []
