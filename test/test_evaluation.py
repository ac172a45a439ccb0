"""evaluate() and `fpcc eval` on tiny hand-built scenes with known answers."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fpcc_ros.cli import main as cli_main
from fpcc_ros.baseline_sweep import DEFAULT_TUNE_SCENES, Setting, default_distances
from fpcc_ros.evaluation import EvalError, SceneError, evaluate, f1_score, load_scene, part_of
from fpcc_ros.pipeline import PipelineConfig, SegmentationResult

TINY_MODEL = Path(__file__).resolve().parent / "data" / "tiny_fpcc.onnx"


def grid(lo, hi, step) -> np.ndarray:
    axes = [np.arange(a, b + step / 2, step) if b > a else np.array([a]) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def patch(x, y, z, step=0.005, size=0.04) -> np.ndarray:
    """The top face of a part as a camera above sees it: a flat square, 9x9 points at 5 mm."""
    return grid((x, y, z), (x + size, y + size, z), step)


# A floor (z = 1, the dominant plane: the baseline removes it) and three parts 15-30 mm above it,
# 25 mm apart. Part faces are parallel to the floor, so the baseline never takes them for walls.
FLOOR = grid((-0.04, -0.04, 1.0), (0.21, 0.21, 1.0), 0.005)          # 51 x 51 = 2601 points
ROW = [patch(0.0, 0.05, 0.98), patch(0.065, 0.05, 0.97), patch(0.13, 0.05, 0.985)]


def write_scene(path: Path, parts, *, extra=None, organized=None, part_radius=0.05,
                part_name: str | None = None) -> np.ndarray:
    """Scene NPZ from parts (labels 1..K); ``extra`` points get label 0. Organized scenes are
    padded with NaN pixels to H*W. Returns the flat ground-truth labels as written."""
    chunks = list(parts) + ([extra] if extra is not None else [])
    xyz = np.concatenate(chunks).astype(np.float32)
    gt = np.concatenate([np.full(len(p), i + 1) for i, p in enumerate(parts)]
                        + ([np.zeros(len(extra), int)] if extra is not None else [])).astype(np.int32)
    if organized:
        h, w = organized
        pad = h * w - len(xyz)
        xyz = np.concatenate([xyz, np.full((pad, 3), np.nan, np.float32)]).reshape(h, w, 3)
        gt = np.concatenate([gt, np.zeros(pad, np.int32)]).reshape(h, w)
    named = {} if part_name is None else {"part_name": np.str_(part_name)}
    np.savez(path, points=xyz, instance=gt, center_score=np.zeros(gt.shape, np.float32),
             part_radius=np.float32(part_radius), **named)
    return gt.reshape(-1)


class GroundTruthPipeline:
    """Stands in for Pipeline: returns each scene's ground truth as its prediction."""

    def __init__(self, truths: list[np.ndarray], part_radius: float = 0.05):
        self.config = PipelineConfig(part_radius=part_radius)
        self.truths = truths
        self.calls: list[tuple[int, float]] = []  # (points, part_radius) per segment call

    def segment(self, xyz: np.ndarray, image_shape=None) -> SegmentationResult:
        self.calls.append((len(xyz), self.config.part_radius))
        labels = next(t for t in self.truths if len(t) == len(xyz)).astype(np.uint32)
        k = int(labels.max())
        return SegmentationResult(labels=labels, center_score=np.zeros(len(xyz), np.float32),
                                  centroids=np.zeros((k, 3)), point_counts=np.ones(k, np.int64),
                                  num_valid=len(xyz), num_network_points=len(xyz))


def test_perfect_prediction_scores_one_and_visible_drops_slivers(tmp_path):
    # organized 48 x 64: visible threshold = round(300 * 3072 / 307200) = 3 points
    sliver = np.array([[0.2, 0.2, 0.95], [0.2, 0.21, 0.95]])         # instance 4: 2 points
    gt = write_scene(tmp_path / "a.npz", [*ROW, sliver], extra=FLOOR, organized=(48, 64))
    report = evaluate([tmp_path / "a.npz"], GroundTruthPipeline([gt]), tolerances=[0.008],
                      min_samples=[1], min_cluster_sizes=[50])
    scene = report.scenes[0]
    assert (scene.gt_instances, scene.visible_gt, scene.visible_threshold) == (4, 3, 3)
    paper, visible = report.fpcc_totals("paper"), report.fpcc_totals("visible")
    assert (paper.true_positives, paper.predictions, paper.ground_truths) == (4, 4, 4)
    assert (visible.true_positives, visible.predictions, visible.ground_truths) == (3, 3, 3)
    for c in (paper, visible):
        assert c.precision == c.recall == c.mucov == c.mwcov == 1.0
    # the baselines at 8 mm link the 5 mm grid and find the parts; the 2-point sliver is under
    # the minimum cluster size (50), so they miss one of 4 under paper and none under visible
    for method in ("euclidean", "dbscan"):
        base_paper = report.baseline_totals("paper", method)
        assert (base_paper.true_positives, base_paper.predictions,
                base_paper.ground_truths) == (3, 3, 4)
        assert report.baseline_totals("visible", method).recall == 1.0
    data = report.to_json()
    assert data["totals"]["visible"]["fpcc"]["precision"] == 1.0
    assert data["scenes"][0]["visible_gt"] == 3
    json.dumps(data)  # serialisable
    assert "a.npz" in report.table() and "visible" in report.summary()


def test_unorganized_scene_uses_300_points(tmp_path):
    big = [patch(x, 0.0, 1.0, step=0.002) for x in (0.0, 0.1, 0.2)]   # 21 x 21 = 441 points
    small = patch(0.3, 0.0, 1.0, step=0.004)                          # 11 x 11 = 121 points
    gt = write_scene(tmp_path / "u.npz", [*big, small])
    report = evaluate([tmp_path / "u.npz"], GroundTruthPipeline([gt]), baseline=False)
    s = report.scenes[0]
    assert (s.visible_threshold, s.gt_instances, s.visible_gt) == (300, 4, 3)
    assert report.tunings == {} and report.baseline_totals("visible") is None
    assert report.to_json()["totals"]["visible"]["baseline"] is None


def test_best_tolerance_is_the_one_that_scores_best(tmp_path):
    """3 mm: below the 5 mm grid, every point alone -> nothing over 50 points (F1 0). 8 mm: the
    three parts exactly (F1 1). 0.2 m: wider than the whole row (0.17 m), one cluster, IoU 1/3
    (F1 0). (Up to 8 mm the clustering voxel, tol/3, is finer than the grid: no downsampling.)"""
    gt = write_scene(tmp_path / "a.npz", ROW, extra=FLOOR, organized=(48, 64))
    report = evaluate([tmp_path / "a.npz"], GroundTruthPipeline([gt]),
                      tolerances=[0.2, 0.003, 0.008], min_samples=[1], min_cluster_sizes=[50])
    tuning = report.tunings[""]
    assert tuning.grid.distances == (0.003, 0.008, 0.2)
    f1 = [f1_score(tuning.totals[Setting("euclidean", t, 1, 50)]["paper"])
          for t in tuning.grid.distances]
    assert f1 == [0.0, 1.0, 0.0]
    chosen = {p: report.baseline_setting("euclidean", p).distance for p in ("paper", "visible")}
    assert chosen == {"paper": 0.008, "visible": 0.008}
    data = report.to_json()["baseline"]["parts"][""]["methods"]["euclidean"]
    assert data["setting"]["visible"] == {"method": "euclidean", "distance_m": 0.008,
                                          "min_cluster_size": 50}
    assert [r.predicted for r in report.scenes[0].baseline] == [3, 3]   # euclidean, dbscan


def test_best_tolerance_uses_counts_summed_over_scenes(tmp_path):
    """Scene a (25 mm gaps) is perfect at 6 and 8 mm; scene b (7 mm gap) only at 6 mm, since
    8 mm merges its two parts. The counts summed over both scenes pick 6 mm."""
    near = [patch(0.0, 0.0, 0.98), patch(0.047, 0.0, 0.98)]           # 7 mm gap
    gt_a = write_scene(tmp_path / "a.npz", ROW, extra=FLOOR)
    gt_b = write_scene(tmp_path / "b.npz", near, extra=FLOOR)
    report = evaluate([tmp_path / "a.npz", tmp_path / "b.npz"],
                      GroundTruthPipeline([gt_a, gt_b]), tolerances=[0.006, 0.008],
                      protocols=["paper"], min_samples=[1], min_cluster_sizes=[50],
                      tune_scenes=2)
    # 6 mm: a 3/3 correct, b 2/2 correct -> TP 5, pred 5, GT 5 (F1 1)
    # 8 mm: a 3/3 correct; b one cluster with IoU exactly 1/2 to each cube (>= 0.5: one match)
    #       -> TP 4, pred 4, GT 5 (F1 8/9)
    totals = {t: report.tunings[""].totals[Setting("euclidean", t, 1, 50)]["paper"]
              for t in report.tunings[""].grid.distances}
    assert (totals[0.006].true_positives, totals[0.006].predictions) == (5, 5)
    assert (totals[0.008].true_positives, totals[0.008].predictions) == (4, 4)
    assert f1_score(totals[0.008]) == pytest.approx(8 / 9)
    assert report.baseline_setting("euclidean", "paper").distance == 0.006
    assert report.tune_scenes == ["a.npz", "b.npz"]


def _bridge_scene(path: Path) -> np.ndarray:
    """test_baseline's bridge case (A, B 8 mm apart; C, D joined by a sparse bridge; a chip) as
    a scene NPZ: DBSCAN at eps 6 mm, min_samples 5, min cluster 50 finds all four parts (F1 1),
    Euclidean clustering at best 6 mm / 50 merges C and D (F1 4/7)."""
    from test_baseline import bridge_scene

    xyz, gt = bridge_scene()
    np.savez(path, points=xyz.astype(np.float32), instance=gt.astype(np.int32),
             center_score=np.zeros(len(gt), np.float32), part_radius=np.float32(0.05))
    return gt.astype(np.int32)


GRID = dict(tolerances=[0.003, 0.006, 0.01], min_cluster_sizes=[1, 50, 1000], protocols=["paper"])


def test_fpcc_is_reported_against_the_stronger_baseline(tmp_path):
    gt = _bridge_scene(tmp_path / "a.npz")
    report = evaluate([tmp_path / "a.npz"], GroundTruthPipeline([gt]), min_samples=[1, 5, 20],
                      **GRID)
    assert report.stronger_baseline("paper") == "dbscan"
    dbscan = report.baseline_setting("dbscan", "paper")
    assert (dbscan.distance, dbscan.min_samples, dbscan.min_cluster_size) == (0.006, 5, 50)
    assert f1_score(report.baseline_totals("paper")) == 1.0
    assert f1_score(report.baseline_totals("paper", "euclidean")) == pytest.approx(4 / 7)
    data = report.to_json()
    assert data["baseline"]["stronger"] == {"paper": "dbscan"}
    assert data["totals"]["paper"]["baseline"] == data["totals"]["paper"]["dbscan"]
    assert data["totals"]["paper"]["euclidean"]["f1"] == pytest.approx(4 / 7)   # both kept
    assert data["scenes"][0]["baseline"]["euclidean"]["paper"]["distance_m"] == 0.006
    summary = report.summary()
    assert "paper   * DBSCAN, eps 6 mm, min_samples 5, min cluster 50: P 1.000 R 1.000 F1 " \
           "1.000" in summary
    assert "paper     Euclidean clustering, tolerance 6 mm, min cluster 50: P 0.667 R 0.500 " \
           "F1 0.571" in summary
    assert "(baseline: DBSCAN, eps 6 mm, min_samples 5, min cluster 50)" in report.table("paper")

    # DBSCAN allowed only min_samples 20 and eps up to 6 mm (no point is core: 7 within 6 mm at
    # most): Euclidean clustering is the stronger
    weak = evaluate([tmp_path / "a.npz"], GroundTruthPipeline([gt]), min_samples=[20],
                    **{**GRID, "tolerances": [0.003, 0.006]})
    assert weak.stronger_baseline("paper") == "euclidean"
    assert weak.baseline_totals("paper") == weak.baseline_totals("paper", "euclidean")
    assert weak.to_json()["totals"]["paper"]["dbscan"]["f1"] == 0.0
    assert "paper   * Euclidean clustering, tolerance 6 mm" in weak.summary()


def test_baselines_are_tuned_on_the_first_scenes_only(tmp_path):
    """Scene b holds four cubes 4 cm across scanned at 10 mm (5^3 = 125 points each, 6 cm apart)
    above the floor: nothing links at 6 mm, so b alone would choose 10 mm. Tuned on a only, the
    report keeps a's choice and shows what it does on b: no part found."""
    gt_a = _bridge_scene(tmp_path / "a.npz")
    cubes = [grid((x, 0.05, 1.02), (x + 0.04, 0.09, 1.06), 0.01) for x in (0.0, 0.1, 0.2, 0.3)]
    gt_b = write_scene(tmp_path / "b.npz", cubes, extra=FLOOR)
    report = evaluate([tmp_path / "a.npz", tmp_path / "b.npz"],
                      GroundTruthPipeline([gt_a, gt_b]), min_samples=[1, 5, 20], tune_scenes=1,
                      **GRID)
    assert report.tune_scenes == ["a.npz"]
    assert report.baseline_setting("dbscan", "paper").distance == 0.006
    on_b = report.scenes[1].baseline_at(report.baseline_setting("dbscan", "paper"))
    assert on_b.counts["paper"].true_positives == 0 and on_b.counts["paper"].ground_truths == 4
    # summed over both scenes: TP 4 (all on a), predictions 4, ground truths 8
    assert f1_score(report.baseline_totals("paper", "dbscan")) == pytest.approx(2 * 4 / (4 + 8))
    assert report.to_json()["scenes"][1]["tuning_scene"] is False


def test_each_part_gets_its_own_tuned_baselines(tmp_path):
    """Scenes of two parts, a folder each as `fpcc eval --data` reads a multi-part set: b's
    cubes (10 mm scan spacing) link only at 12 mm, where a's parts A and B (8 mm apart) merge.
    One tuning for the whole set, on its first scene, found none of b's cubes (the test above);
    each part tuned on its own first scene finds every part of both."""
    for folder in ("part_a", "part_b"):
        (tmp_path / folder).mkdir()
    gt_a = _bridge_scene(tmp_path / "part_a" / "a.npz")
    cubes = [grid((x, 0.05, 1.02), (x + 0.04, 0.09, 1.06), 0.01) for x in (0.0, 0.1, 0.2, 0.3)]
    gt_b = write_scene(tmp_path / "part_b" / "b.npz", cubes, extra=FLOOR)
    report = evaluate([tmp_path / "part_a" / "a.npz", tmp_path / "part_b" / "b.npz"],
                      GroundTruthPipeline([gt_a, gt_b]), min_samples=[1, 5, 20], tune_scenes=1,
                      root=tmp_path, **{**GRID, "tolerances": [0.003, 0.006, 0.012]})
    assert list(report.tunings) == ["part_a", "part_b"]
    assert report.tune_scenes == ["part_a/a.npz", "part_b/b.npz"]
    assert report.baseline_setting("dbscan", "paper", "part_a").distance == 0.006
    assert report.baseline_setting("dbscan", "paper", "part_b").distance == 0.012
    assert report.baseline_setting("dbscan", "paper") is None   # several parts: name one
    on_b = report.scenes[1].baseline_at(report.baseline_setting("dbscan", "paper", "part_b"))
    assert on_b.counts["paper"].true_positives == 4
    assert f1_score(report.baseline_totals("paper", "dbscan")) == 1.0   # 4 of a + 4 of b
    data = report.to_json()
    assert data["scenes"][1]["part"] == "part_b" and data["scenes"][1]["tuning_scene"] is True
    assert data["baseline"]["parts"]["part_b"]["methods"]["dbscan"]["setting"]["paper"][
        "distance_m"] == 0.012
    assert "each tuned per part (2 parts)" in report.summary()
    assert "part_b: DBSCAN, eps 12 mm, min_samples 1, min cluster 1: P 1.000 R 1.000 F1 1.000 " \
           "(FPCC F1 1.000)" in report.summary()


def test_a_scene_names_its_part_else_its_folder_does(tmp_path):
    (tmp_path / "sub").mkdir()
    write_scene(tmp_path / "sub" / "named.npz", ROW, part_name="gear_shaft")
    write_scene(tmp_path / "sub" / "plain.npz", ROW)
    write_scene(tmp_path / "top.npz", ROW)
    assert part_of(tmp_path / "sub" / "named.npz", tmp_path) == "gear_shaft"
    assert part_of(tmp_path / "sub" / "plain.npz", tmp_path) == "sub"
    assert part_of(tmp_path / "top.npz", tmp_path) == ""
    assert part_of(tmp_path / "sub" / "plain.npz") == ""   # no root: one group


def test_tuning_scene_count_must_be_positive(tmp_path):
    gt = write_scene(tmp_path / "a.npz", ROW)
    with pytest.raises(EvalError, match="tuning scenes 0"):
        evaluate([tmp_path / "a.npz"], GroundTruthPipeline([gt]), tune_scenes=0)


def test_scene_part_radius_unless_fixed(tmp_path):
    gts = [write_scene(tmp_path / "a.npz", ROW, part_radius=0.03),
           write_scene(tmp_path / "b.npz", ROW[:2], part_radius=0.07)]
    fake = GroundTruthPipeline(gts)
    evaluate([tmp_path / "a.npz", tmp_path / "b.npz"], fake, baseline=False)
    assert [r for _, r in fake.calls] == pytest.approx([0.03, 0.07])
    assert fake.config.part_radius == 0.05                              # caller's untouched
    fake.calls.clear()
    report = evaluate([tmp_path / "a.npz", tmp_path / "b.npz"], fake, baseline=False,
                      fixed_part_radius=True)
    assert [r for _, r in fake.calls] == [0.05, 0.05]
    assert report.to_json()["pipeline"]["part_radius_source"] == "fixed"


def test_default_distances_scale_with_part_radius():
    # 10 steps, ratio 10 ** (1/9) = 1.2916, from 2 % to 20 % of d_max, rounded to 0.1 mm
    assert default_distances(0.1) == pytest.approx([0.002, 0.0026, 0.0033, 0.0043, 0.0056,
                                                    0.0072, 0.0093, 0.012, 0.0155, 0.02])
    assert default_distances(0.05)[0] == 0.001 and default_distances(0.05)[-1] == 0.01


def test_scenes_without_instances_skipped_then_error(tmp_path):
    gt = write_scene(tmp_path / "a.npz", ROW)
    np.savez(tmp_path / "empty.npz", points=FLOOR.astype(np.float32),
             instance=np.zeros(len(FLOOR), np.int32), part_radius=np.float32(0.05))
    warnings: list[str] = []
    report = evaluate([tmp_path / "a.npz", tmp_path / "empty.npz"], GroundTruthPipeline([gt]),
                      baseline=False, warn=warnings.append)
    assert [s.scene for s in report.scenes] == ["a.npz"]
    assert report.skipped[0][0] == "empty.npz" and "empty.npz" in warnings[0]
    with pytest.raises(EvalError, match="none of the 1 scenes has ground-truth instances"):
        evaluate([tmp_path / "empty.npz"], GroundTruthPipeline([gt]), baseline=False)


def test_malformed_scene_names_the_key(tmp_path):
    np.savez(tmp_path / "bad.npz", points=np.zeros((10, 3), np.float32), part_radius=0.05)
    with pytest.raises(SceneError, match="missing key 'instance'"):
        evaluate([tmp_path / "bad.npz"], GroundTruthPipeline([]), baseline=False)
    np.savez(tmp_path / "norad.npz", points=np.zeros((10, 3), np.float32),
             instance=np.ones(10, np.int32))
    with pytest.raises(SceneError, match="part_radius"):
        evaluate([tmp_path / "norad.npz"], GroundTruthPipeline([]), baseline=False)


# -- the command ----------------------------------------------------------------------------------
needs_model = pytest.mark.skipif(not TINY_MODEL.exists(), reason="test/data/tiny_fpcc.onnx missing")


def _two_scenes(data: Path) -> None:
    data.mkdir()
    write_scene(data / "s1.npz", ROW, extra=FLOOR, organized=(48, 64))
    # unorganized, parts at 2 mm (21 x 21 = 441 points each, over the 300-point visible limit)
    write_scene(data / "s2.npz", [patch(0.0, 0.05, 0.98, 0.002), patch(0.065, 0.05, 0.97, 0.002)],
                extra=FLOOR)


@needs_model
def test_command_end_to_end(tmp_path, capsys):
    data = tmp_path / "scenes"
    _two_scenes(data)
    rc = cli_main(["eval", "--data", str(data), "--model", str(TINY_MODEL),
                   "--baseline-tolerances", "0.003", "0.008"])
    out = capsys.readouterr().out
    assert rc == 0
    report = json.loads((data / "eval_tiny_fpcc.json").read_text())
    assert {"format", "model", "pipeline", "protocols", "totals", "baseline", "timings_ms",
            "scenes", "skipped"} <= set(report)
    assert report["protocols"] == ["paper", "visible"]
    assert [s["scene"] for s in report["scenes"]] == ["s1.npz", "s2.npz"]
    assert report["totals"]["visible"]["fpcc"]["ground_truths"] == 5
    euclid = report["baseline"]["parts"][""]["methods"]["euclidean"]["setting"]["visible"]
    assert euclid["distance_m"] == 0.008
    assert report["baseline"]["parts"][""]["tune_scenes"] == ["s1.npz", "s2.npz"]   # of 3
    assert report["totals"]["visible"]["baseline"]["precision"] == 1.0
    assert {"euclidean", "dbscan"} <= set(report["totals"]["visible"])
    assert "tuned on 2 scene(s) (s1.npz, s2.npz)" in out and DEFAULT_TUNE_SCENES == 3
    assert report["model"]["name"] == "tiny_fpcc"
    assert "s1.npz" in out and "summary over 2 scenes" in out


@needs_model
def test_command_reads_sub_folders(tmp_path):
    """A set of several parts is one folder per part (scripts/make_default_dataset.sh), with
    the same file names in each: every scene counts, named by its path below --data."""
    data = tmp_path / "val"
    data.mkdir()
    _two_scenes(data / "part_a")
    _two_scenes(data / "part_b")
    out = tmp_path / "report.json"
    rc = cli_main(["eval", "--data", str(data), "--model", str(TINY_MODEL), "--out", str(out),
                   "--no-baseline"])
    assert rc == 0
    report = json.loads(out.read_text())
    assert [s["scene"] for s in report["scenes"]] == ["part_a/s1.npz", "part_a/s2.npz",
                                                      "part_b/s1.npz", "part_b/s2.npz"]
    assert report["totals"]["visible"]["fpcc"]["ground_truths"] == 10   # 5 per folder


@needs_model
def test_command_options(tmp_path, capsys):
    data = tmp_path / "scenes"
    _two_scenes(data)
    out = tmp_path / "r" / "report.json"
    rc = cli_main(["eval", "--data", str(data), "--model", str(TINY_MODEL), "--out", str(out),
                   "--limit", "1", "--protocol", "paper", "--no-baseline", "--part-radius", "0.04"])
    assert rc == 0
    report = json.loads(out.read_text())
    assert report["protocols"] == ["paper"] and len(report["scenes"]) == 1
    assert report["baseline"] is None and report["totals"]["paper"]["baseline"] is None
    assert report["scenes"][0]["part_radius"] == 0.04


def test_report_goes_to_the_working_directory_when_the_data_is_read_only(tmp_path, monkeypatch):
    from fpcc_ros.commands import evaluate as command

    data = tmp_path / "scenes"
    data.mkdir()
    model = Path("models/m.onnx")
    assert command.default_report_path(data, model) == data / "eval_m.json"
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    # root may write anywhere, so the read-only folder is simulated through os.access
    monkeypatch.setattr(command.os, "access", lambda path, mode: Path(path) != data)
    assert command.default_report_path(data, model) == work / "eval_m.json"


def test_command_errors(tmp_path, capsys):
    assert cli_main(["eval", "--data", str(tmp_path / "nope")]) == 2
    assert "is not a directory" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert cli_main(["eval", "--data", str(tmp_path / "empty")]) == 2
    assert "no scene .npz or .txt files" in capsys.readouterr().err


@needs_model
def test_command_errors_with_model(tmp_path, capsys):
    data = tmp_path / "scenes"
    data.mkdir()
    np.savez(data / "e.npz", points=FLOOR.astype(np.float32),
             instance=np.zeros(len(FLOOR), np.int32), part_radius=np.float32(0.05))
    assert cli_main(["eval", "--data", str(data), "--model", str(TINY_MODEL)]) == 2
    err = capsys.readouterr().err
    assert "skipping" in err and "no ground-truth instances" in err
    # an ONNX whose card disagrees with it (k = 8 in the card, 16 in the graph)
    model = tmp_path / "m.onnx"
    shutil.copy(TINY_MODEL, model)
    card = json.loads(TINY_MODEL.with_suffix(".json").read_text())
    model.with_suffix(".json").write_text(json.dumps({**card, "k": 8}))
    _two_scenes(tmp_path / "ok")
    assert cli_main(["eval", "--data", str(tmp_path / "ok"), "--model", str(model)]) == 2
    err = capsys.readouterr().err
    assert "not an FPCC-Net matching its card" in err and "knn" in err


def _as_text(npz: Path, txt: Path, columns: str) -> None:
    """The NPZ scene's finite points as a labelled text scene in the named column order."""
    z = np.load(npz)
    xyz, gt = z["points"].reshape(-1, 3), z["instance"].reshape(-1)
    keep = np.isfinite(xyz).all(axis=1)
    score = np.full(keep.sum(), 0.5)
    cols = [xyz[keep], score[:, None], gt[keep][:, None]] if columns == "paper" else \
        [xyz[keep], gt[keep][:, None], score[:, None]]
    np.savetxt(txt, np.hstack(cols), fmt="%.6f")


def test_text_scenes_are_evaluated_like_their_npz_with_a_fixed_part_radius(tmp_path):
    npz = tmp_path / "a.npz"
    gt = write_scene(npz, ROW, extra=FLOOR)
    for columns in ("paper", "peer"):
        txt = tmp_path / f"a_{columns}.txt"
        _as_text(npz, txt, columns)
        scene = load_scene(txt, columns)
        assert scene.part_radius is None and scene.shape == (len(gt),)
        np.testing.assert_array_equal(scene.instance, gt)
        pipeline = GroundTruthPipeline([gt])
        sweep = dict(tolerances=[0.008], min_samples=[1, 5], min_cluster_sizes=[50])
        from_text = evaluate([txt], pipeline, fixed_part_radius=True, columns=columns, **sweep)
        from_npz = evaluate([npz], pipeline, **sweep)
        assert from_text.fpcc_totals("visible") == from_npz.fpcc_totals("visible")
        for method in ("euclidean", "dbscan"):
            assert from_text.baseline_totals("visible", method) == \
                from_npz.baseline_totals("visible", method)
    # without a fixed radius: a clear error naming the fix
    with pytest.raises(SceneError, match="text scene has no part radius.*--part-radius"):
        evaluate([tmp_path / "a_peer.txt"], GroundTruthPipeline([gt]), columns="peer")
    # x y z only: no labels to score against
    np.savetxt(tmp_path / "xyz.txt", np.load(npz)["points"][:20], fmt="%.4f")
    with pytest.raises(SceneError, match="no 'instance' column.*--columns peer"):
        load_scene(tmp_path / "xyz.txt")


def test_peer_generators_scene_evaluates_through_the_command(shared_dir, tmp_path, capsys):
    """The third-party gear-shaft scene (z-up world frame, x y z instance center_score): read,
    turned into the camera's view, scored against its 19 parts."""
    data = tmp_path / "peer"
    data.mkdir()
    (data / "scene.txt").symlink_to(shared_dir / "data" / "peer" / "gear_shaft_scene_020.txt")
    out = tmp_path / "r.json"
    assert cli_main(["eval", "--data", str(data), "--columns", "peer", "--part-radius", "0.242",
                     "--no-baseline", "--protocol", "visible", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["scenes"][0]["gt_instances"] == 19
    assert report["totals"]["visible"]["fpcc"]["predictions"] > 0
