"""`fpcc bench`: a smoke run on one tiny generated scene with the tiny model, the report's
derived figures on hand-made numbers, and the DDS summary's queue verdict on synthetic timings."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fpcc_ros import bench
from fpcc_ros.bench_dds import parse_node_log, summarise
from fpcc_ros.metrics import InstanceCounts
from fpcc_ros.onnx_model import FpccModel
from fpcc_ros.pipeline import Pipeline, PipelineConfig

REPO = Path(__file__).resolve().parent.parent
TINY = REPO / "test" / "data" / "tiny_fpcc.onnx"


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("bench_cache")


@pytest.fixture(scope="module")
def tiny_scene(cache) -> list[bench.BenchScene]:
    pytest.importorskip("pybullet")
    return bench.synth_scenes([4], cache=cache, crops=(0.5,), width=96, height=72)


@pytest.fixture(scope="module")
def tiny_pipeline() -> Pipeline:
    model = FpccModel(TINY, threads=1)
    return Pipeline(model, PipelineConfig.from_card(model.card))


def test_scenes_are_cached_and_organized(tiny_scene, cache, monkeypatch):
    scene, crop = tiny_scene
    assert (scene.kind, crop.kind) == ("synth", "crop")
    assert (int(scene.msg.height), int(scene.msg.width)) == (72, 96)
    assert scene.gt is not None and scene.gt.shape == (72 * 96,)
    assert scene.center_score is not None and scene.center_score.shape == (72 * 96,)
    # the crop is the central window of half the area: round(72 * 0.707) x round(96 * 0.707)
    assert (int(crop.msg.height), int(crop.msg.width)) == (51, 68)
    assert len(list(cache.glob("*.npz"))) == 1
    # a second call reads the cache instead of simulating again
    import fpcc_ros.training.synth as synth

    monkeypatch.setattr(synth, "generate_scene", lambda *a, **k: pytest.fail("regenerated"))
    again = bench.synth_scenes([4], cache=cache, crops=(), width=96, height=72)
    assert np.array_equal(again[0].gt, scene.gt)


def test_bench_smoke(tiny_scene, tiny_pipeline, tmp_path):
    scene = tiny_scene[0]
    report = bench.run_bench(tiny_pipeline, tiny_scene, runs=2, full_res=True,
                             postprocess_scene=scene)
    assert [r.name for r in report.scenes] == [s.name for s in tiny_scene]
    run = report.scenes[0]
    for stage in ("decode", "valid", "downsample", "inference", "nms", "cluster", "encode", "total"):
        assert len(run.stages_ms[stage]) == 2, stage
        assert run.stat(stage) <= run.stat(stage, 90)
    assert run.valid_points == int(np.isfinite(
        np.frombuffer(bytes(scene.msg.data), np.float32).reshape(-1, 4)[:, :3]).all(1).sum())
    assert run.counts is not None and 0.0 <= run.counts.precision <= 1.0
    assert run.full_res is not None and run.full_res["network_points"] == run.valid_points
    assert run.peak_rss_mb > 10
    post = report.postprocess
    assert post["points"] == min(100_000, run.valid_points) and post["total_ms"]["median"] > 0
    # embeddings made from the ground truth: every center found joins its own instance
    assert post["accuracy"]["precision"] > 0.5

    # the clustering step as the pipeline runs it: prototypes and merging keep the GT instances
    full = bench.measure_postprocess(bench.postprocess_case(scene), 2, 0.6, 1.0, 1.0,
                                     center_prototype=0.5, center_merge=0.5)
    assert full["center_prototype"] == 0.5 and full["assign_ms"]["median"] > 0
    assert full["accuracy"]["precision"] > 0.5

    out = bench.write_json(report, tmp_path / "bench.json")
    data = json.loads(out.read_text())
    assert data["format"] == bench.REPORT_FORMAT
    assert data["scenes"][0]["stages_ms"]["total"]["runs"] == run.stages_ms["total"]
    assert any(g["goal"].startswith("NMS + clustering") for g in data["goals"])
    again = bench.report_from_json(data)   # re-rendered from the file, same tables
    assert again.markdown() == report.markdown() and again.table() == report.table()
    png = bench.plot(report, tmp_path / "bench.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    md = report.markdown()
    assert md.count("\n| synth/") == 2 and "| goal | measured |" in md
    text = report.table() + report.summary()
    assert scene.name in text and "goals:" in text
    assert report.machine["speed_probe_ms"] > 0 and "speed probe" in report.summary()


def test_a_slow_machine_is_named_in_the_notes(tiny_scene, tiny_pipeline, monkeypatch):
    """The speed probe far above its host kind's idle reference: the report says its timings
    are inflated by load and by how much; at the reference speed it says nothing. An idle AVX2
    host (its probe ~1.8x the AVX-512 table's) is not called loaded."""
    assert bench.REFERENCE_PROBE_MS_AVX2 > bench.SLOW_PROBE_FACTOR * bench.REFERENCE_PROBE_MS
    hosts = ((["avx2", "fma", "avx512f"], bench.REFERENCE_PROBE_MS),
             (["avx2", "fma"], bench.REFERENCE_PROBE_MS_AVX2),
             (None, bench.REFERENCE_PROBE_MS))     # flags unknown: the table's reference
    for vector, reference in hosts:
        for probe, noted in ((2 * reference, True), (reference, False)):
            monkeypatch.setattr(bench, "machine_info", lambda pipeline, v=vector, p=probe: {
                "cpu": "test", "cpus": 2, "cpu_vector": v, "speed_probe_ms": p})
            report = bench.run_bench(tiny_pipeline, tiny_scene[:1], runs=1)
            notes = [n for n in report.notes if "speed probe" in n]
            assert bool(notes) == noted, (vector, probe, report.notes)
            if noted:
                assert "2.0x inflated by load" in notes[0] and f"~{reference:g} ms" in notes[0]
            assert f"~{reference:g})" in report.summary()


def _run(name, kind, parts, valid, total_ms, counts=None, full=None):
    return bench.SceneRun(name=name, kind=kind, points=640 * 480, valid_points=valid,
                          network_points=valid // 10, gt_instances=parts, num_parts=parts,
                          predicted=parts or 0, stages_ms={"total": list(total_ms)},
                          counts=counts, peak_rss_mb=100.0, full_res=full)


def test_report_growth_linearity_and_goals():
    fast = InstanceCounts(true_positives=18, predictions=20, ground_truths=20)
    full = {"accuracy": {"true_positives": 19, "predictions": 20, "ground_truths": 20}}
    report = bench.BenchReport(scenes=[
        _run("a", "synth", 5, 100_000, [100, 110, 120]),
        _run("b", "synth", 20, 200_000, [150, 150, 160], counts=fast, full=full),
        _run("c", "synth", 40, 300_000, [200, 210, 230]),
    ], machine={}, model={}, config={}, runs=3)
    g = report.growth()
    assert (g["from_parts"], g["to_parts"]) == (5, 40)
    assert g["growth"] == pytest.approx(210 / 110 - 1)
    lin = report.linearity()  # medians 110, 150, 210 at 100k, 200k, 300k: slope 50 ms / 100k
    assert lin["ms_per_100k_valid_points"] == pytest.approx(50.0)
    assert lin["intercept_ms"] == pytest.approx(470 / 3 - 100)  # mean 156.7 ms at 200k
    goals = {x["goal"]: x for x in report.goals()}
    e2e = goals["end to end, cluttered bin (20-30 parts), median"]
    assert e2e["value"] == 150 and e2e["ok"] is True
    acc = next(x for k, x in goals.items() if k.startswith("precision/recall vs full"))
    assert acc["value"] == pytest.approx(5.0) and acc["ok"] is False  # recall 0.90 vs 0.95
    loss = goals["  the same, loss only (fast path below full resolution)"]
    assert loss["value"] == pytest.approx(5.0) and loss["ok"] is False
    # a fast path better than full resolution misses the two-sided goal but loses nothing
    better = {"accuracy": {"true_positives": 10, "predictions": 20, "ground_truths": 20}}
    report_better = bench.BenchReport(scenes=[
        _run("b", "synth", 20, 200_000, [150], counts=fast, full=better)],
        machine={}, model={}, config={}, runs=1)
    better_goals = {x["goal"]: x for x in report_better.goals()}
    assert better_goals["precision/recall vs full resolution, cluttered bins (points)"]["ok"] \
        is False
    loss = better_goals["  the same, loss only (fast path below full resolution)"]
    assert loss["value"] == 0.0 and loss["ok"] is True
    growth = next(x for k, x in goals.items() if k.startswith("latency growth"))
    assert growth["ok"] is False


def _timings(rate, seconds, process_s, queue):
    """Send times at ``rate``; a node taking ``process_s`` per frame either serves frames in
    order (a queue) or always takes the newest one sent before it becomes free."""
    sent = {i: i / rate for i in range(int(seconds * rate))}
    arrivals, free = {}, 0.0
    pending = sorted(sent)
    while pending:
        if queue:
            s = pending.pop(0)
        else:
            ready = [p for p in pending if sent[p] <= max(free, sent[pending[0]])]
            s = ready[-1]
            pending = [p for p in pending if p > s]
        start = max(free, sent[s])
        free = start + process_s
        arrivals[s] = {"segmented_points": free, "instances": free + 0.001,
                       "instance_markers": free + 0.002}
    return sent, arrivals


@pytest.mark.parametrize("queue", [False, True])
def test_dds_summary_tells_a_queue_from_dropping(queue):
    sent, arrivals = _timings(rate=10, seconds=20, process_s=0.25, queue=queue)
    r = summarise(10, 20.0, sent, arrivals, rss=[(0.0, 300.0), (1.0, 310.0)], peak_rss_mb=320.0,
                  log="", exit_code=0)
    assert r["keeps_up"] is False
    assert r["processing_period_ms"] == pytest.approx(250, abs=1)
    if queue:   # every frame is served, each waiting longer: the age grows ~ (1 - 10*0.025)/s
        assert r["dropped"] == 0
        assert r["age_trend_ms_per_s"] > 500
        assert r["no_queue"] is False
    else:       # about 1 frame in 2.5 answered; ages stay within about one period
        assert 70 <= r["outputs"] <= 90 and r["dropped"] == 200 - r["outputs"]
        assert r["latency_ms"]["max"] <= 2 * 250 + 1
        assert abs(r["age_trend_ms_per_s"]) < 5
        assert r["no_queue"] is True


def test_dds_summary_gives_the_nodes_page_faults_per_output_frame():
    sent, arrivals = _timings(rate=5, seconds=4, process_s=0.1, queue=False)
    r = summarise(5, 4.0, sent, arrivals, rss=[], peak_rss_mb=300.0, log="", exit_code=0,
                  minor_faults=4000)
    assert r["outputs"] == 20
    assert r["node_minor_faults_per_output"] == pytest.approx(200.0)
    assert summarise(5, 4.0, sent, arrivals, rss=[], peak_rss_mb=300.0, log="",
                     exit_code=0)["node_minor_faults_per_output"] is None


def test_minor_faults_reads_this_process_and_grows_with_fresh_memory():
    import os

    import numpy as np

    from fpcc_ros.bench_dds import minor_faults

    before = minor_faults(os.getpid())
    touched = np.ones(64 << 20, np.uint8)   # 64 MB mapped afresh: beyond any kept free memory
    after = minor_faults(os.getpid())
    assert before is not None and after - before >= 16, (before, after, touched[0])
    assert minor_faults(2 ** 22 + 12345) is None   # no such process


def test_parse_node_log():
    log = ("[INFO] 12 frames out, 3 stale dropped, 0 invalid, 0 failed; latency median 181 ms, "
           "last 20 instances\n[INFO] 30 frames out ...; latency median 175.5 ms, last 19\n"
           "[INFO] totals: received 40, published 31, invalid 0, failed 0, dropped_stale 9, "
           "skipped_old 0, dropped_at_shutdown 0\n")
    parsed = parse_node_log(log)
    assert parsed["received"] == 40 and parsed["published"] == 31
    assert parsed["dropped_stale"] == 9 and parsed["node_latency_median_ms"] == 175.5


def test_cli_parses_and_runs_without_scenes(capsys, tmp_path):
    from fpcc_ros.cli import main

    code = main(["bench", "--scenes", "none", "--model", str(TINY), "--json",
                 str(tmp_path / "r.json")])
    assert code == 0
    out = capsys.readouterr().out
    assert "goals:" in out and json.loads((tmp_path / "r.json").read_text())["scenes"] == []
    with pytest.raises(SystemExit):
        main(["bench", "--scenes", "demo,nope"])


def test_variants_are_parsed_run_and_tabled(tiny_scene, tiny_pipeline):
    assert bench.parse_variant("block_halo=0.5,block_size=4096") == {"block_halo": 0.5,
                                                                      "block_size": 4096}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        bench.parse_variant("block_halo")
    report = bench.run_bench(tiny_pipeline, tiny_scene[:1], runs=1)
    bench.run_variants(report, tiny_pipeline, tiny_scene[:1], ["block_halo=0"], runs=1)
    (variant,) = report.variants
    assert variant["config"]["block_halo"] == 0 and len(variant["scenes"]) == 1
    # no halo: exactly the floor-free points go through the network, fewer than with one
    assert variant["scenes"][0].inferred_points <= report.scenes[0].inferred_points
    assert "block_halo=0" in report.variants_table()
    assert json.dumps(report.to_json(), default=bench._json_default)


def test_postprocess_case_shows_the_paper_rule_beside_extra_clustering_steps(tiny_scene,
                                                                              tiny_pipeline):
    import copy

    pipeline = copy.copy(tiny_pipeline)
    pipeline.config = tiny_pipeline.config.replace(center_prototype=0.5)
    report = bench.run_bench(pipeline, tiny_scene[:1], runs=1, postprocess_scene=tiny_scene[0])
    assert report.postprocess["center_prototype"] == 0.5
    plain = report.postprocess["paper_rule"]
    assert plain["center_prototype"] == 0 and plain["total_ms"]["median"] > 0
    assert any("paper's clustering" in g["goal"] for g in report.goals())
    assert "with the paper's clustering" in report.summary()
    again = bench.report_from_json(json.loads(json.dumps(report.to_json())))
    assert again.summary() == report.summary()


def test_postprocess_case_times_the_chunk_loops_on_one_thread_too(tiny_scene, tiny_pipeline):
    report = bench.run_bench(tiny_pipeline, tiny_scene[:1], runs=1,
                             postprocess_scene=tiny_scene[0])
    one, default = report.postprocess["one_thread"], report.postprocess
    # the same work, so the same centers and labels; only the time may differ
    assert one["centers"] == default["centers"] and one["accuracy"] == default["accuracy"]
    assert one["assign_ms"]["median"] > 0
    assert "chunk loops on one thread" in report.summary()


def test_postprocess_case_uses_fixed_nms_settings_not_the_cards(tiny_scene, tiny_pipeline):
    """The NMS + clustering figure must compare across calibrations: a card with another θ/γ
    changes the gate and clustering steps only, not which centers the case times."""
    import copy

    pipeline = copy.copy(tiny_pipeline)
    pipeline.config = tiny_pipeline.config.replace(score_threshold=0.95, screening_factor=3.0)
    report = bench.run_bench(pipeline, tiny_scene[:1], runs=1, postprocess_scene=tiny_scene[0])
    post = report.postprocess
    assert post["score_threshold"] == bench.POSTPROCESS_SCORE_THRESHOLD != 0.95
    assert post["screening_factor"] == bench.POSTPROCESS_SCREENING_FACTOR != 3.0
    at_card = bench.measure_postprocess(bench.postprocess_case(tiny_scene[0]), 1, 0.95, 3.0,
                                        pipeline.config.feature_gate)
    assert post["centers"] > at_card["centers"]
    assert f"θ {bench.POSTPROCESS_SCORE_THRESHOLD}" in report.summary()


@pytest.mark.parametrize("graph, hint", [("", "not rewritten"),
                                         ("global-max-pool", "predates the max-first"),
                                         ("global-max-pool,max-first", "no global_stride"),
                                         ("global-max-pool,max-first,global-stride", None)])
def test_a_model_without_the_latest_graph_rewrite_is_named(tiny_scene, tiny_pipeline,
                                                           monkeypatch, graph, hint):
    monkeypatch.setattr(tiny_pipeline.model, "graph_notes", graph)
    notes = " ".join(bench.run_bench(tiny_pipeline, tiny_scene[:1], runs=1).notes)
    if hint is None:
        assert "optimize_onnx" not in notes
    else:
        assert hint in notes and "scripts/optimize_onnx.py" in notes


CPUINFO = """processor\t: 0
model name\t: AMD EPYC
flags\t\t: fpu sse2 avx fma avx2 bmi2 {extra}
processor\t: 1
model name\t: AMD EPYC
flags\t\t: fpu sse2 avx fma avx2 bmi2 avx512f avx512_bf16
"""


def test_cpu_description_reads_the_first_cpus_vector_extensions():
    assert bench.cpu_description(CPUINFO.format(extra="")) == ("AMD EPYC", ["avx2", "fma"])
    _, vector = bench.cpu_description(CPUINFO.format(extra="avx512f avx512_vnni"))
    assert vector == ["avx2", "fma", "avx512f", "avx512_vnni"]
    assert bench.cpu_description("") == ("", [])


def test_a_cpu_without_avx512_is_named_in_the_notes(tiny_scene, tiny_pipeline, monkeypatch):
    """Timings from a host without AVX-512 are another machine's: the report says so; with
    AVX-512, or where the flags are unknown, it says nothing."""
    for vector, noted in ((["avx2", "fma"], True), (["avx2", "avx512f"], False), (None, False)):
        monkeypatch.setattr(bench, "machine_info",
                            lambda pipeline, vector=vector: {"cpu": "test", "cpus": 2,
                                                             "cpu_vector": vector})
        report = bench.run_bench(tiny_pipeline, tiny_scene[:1], runs=1)
        assert any("no AVX-512" in n for n in report.notes) == noted
        named = vector is not None
        assert ("(avx2" in report.summary()) == named and ("(avx2" in report.markdown()) == named


def test_a_global_stride_is_named_in_the_report(tiny_scene, tiny_pipeline, monkeypatch):
    """An approximate network is never reported as the plain one: the stride in use is on the
    model line of the summary and on the markdown's machine line."""
    report = bench.run_bench(tiny_pipeline, tiny_scene[:1], runs=1)
    assert "1 in 4 points" not in report.summary() + report.markdown()
    report.config["global_stride"] = 4
    assert "global feature over 1 in 4 points" in report.summary()
    assert "global feature over 1 in 4 points" in report.markdown()


def test_the_cpu_vendor_is_named_beside_the_timings(tiny_scene, tiny_pipeline, monkeypatch):
    assert bench.cpu_vendor("vendor_id\t: GenuineIntel\nmodel name\t: Intel(R) Xeon(R)\n") == \
        "GenuineIntel"
    assert bench.cpu_vendor("") == ""
    monkeypatch.setattr(bench, "machine_info", lambda pipeline: {
        "cpu": "Intel(R) Xeon(R) Platinum", "cpu_vendor": "GenuineIntel", "cpus": 2,
        "cpu_vector": ["avx2", "avx512f", "amx_bf16"]})
    report = bench.run_bench(tiny_pipeline, tiny_scene[:1], runs=1)
    assert "GenuineIntel Intel(R) Xeon(R) Platinum (avx2 avx512f amx_bf16)" in report.summary()
    assert "GenuineIntel" in report.markdown()


def test_the_models_health_is_printed_and_a_collapsed_one_named(tiny_scene, tiny_pipeline,
                                                               monkeypatch):
    report = bench.run_bench(tiny_pipeline, tiny_scene[:1], runs=1)
    assert "model health: 0 tiny weights zeroed at load (0 denormal); no dead channels" in \
        report.summary()
    assert not any("collapsed" in n for n in report.notes)
    monkeypatch.setattr(tiny_pipeline.model, "dead_channels", {"glob_w": (892, 1024)})
    report = bench.run_bench(tiny_pipeline, tiny_scene[:1], runs=1)
    assert "dead channels: glob_w 892/1024 (87%)" in report.summary()
    assert any("collapsed" in n for n in report.notes)
