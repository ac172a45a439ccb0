"""Malformed clouds through the live node (issue: never crash, never lose a frame silently).

The catalogue test checks the mutation catalogue itself against msg_tools' validator: every
malformed kind is rejected with a message containing its phrase, every well-formed kind is read
exactly as the factory packed it. The live test is a shortened scripts/fuzz_node.py run (the full
run sends 2,000+ messages): every kind at least twice, one two-million-point cloud, over DDS.
"""
import os
import sys

import numpy as np
import pytest

from msg_tools.point_cloud2 import CloudFormatError, read_xyz, validate_cloud

import cloud_factory as cf
from conftest import REPO

sys.path.insert(0, str(REPO / "scripts"))
import fuzz_node  # noqa: E402

SEED = int(os.environ.get("FPCC_FUZZ_SEED", "0"))


@pytest.mark.parametrize("kind", cf.KINDS, ids=lambda k: k.name)
def test_catalogue_kind_agrees_with_the_contract_and_the_validator(kind):
    rng = np.random.default_rng(SEED)
    verdicts = []
    for _ in range(25):
        msg = kind.build(rng)
        valid = cf.expected_valid(msg)
        verdicts.append(valid)
        if kind.valid is not None:
            assert valid == kind.valid
        if valid:
            validate_cloud(msg)
            np.testing.assert_array_equal(read_xyz(msg), cf.true_xyz(msg))
        else:
            with pytest.raises(CloudFormatError) as err:
                validate_cloud(msg)
            assert kind.warning in str(err.value)
            assert err.value.kind and " " not in err.value.kind  # a fixed key, not text


def test_random_header_edits_produce_both_verdicts():
    rng = np.random.default_rng(SEED)
    kind = cf.BY_NAME["random_header_edits"]
    verdicts = [cf.expected_valid(kind.build(rng)) for _ in range(300)]
    assert 0 < sum(verdicts) < len(verdicts)


def test_expected_valid_on_hand_made_headers():
    """The independent contract statement itself, on cases worked out by hand."""
    good = cf.make_cloud(np.zeros((2, 3, 3), np.float32), "xyz32")   # 2x3, point_step 16
    assert cf.expected_valid(good)
    assert (good.height, good.width, good.point_step, good.row_step, len(good.data)) == \
        (2, 3, 16, 48, 96)
    assert not cf.expected_valid(cf.clone(good, data=bytes(95)))
    assert not cf.expected_valid(cf.clone(good, row_step=47, data=bytes(94)))
    assert cf.expected_valid(cf.clone(good, row_step=50, data=bytes(100)))   # row padding
    assert not cf.expected_valid(cf.clone(good, point_step=11, row_step=33, data=bytes(66)))
    assert cf.expected_valid(cf.clone(good, point_step=12, row_step=36, data=bytes(72)))


@pytest.mark.ros
def test_fuzzed_node_never_crashes_and_publishes_only_for_valid_clouds(tmp_path):
    report = fuzz_node.run_fuzz(messages=200, big=1, seed=SEED, log_path=tmp_path / "node.log")
    print(report.table())
    kinds_sent = {name for name, row in report.rows.items() if row.sent}
    assert {k.name for k in cf.KINDS} | {"two_million_points"} <= kinds_sent
    assert report.crashes == 0 and report.exit_code == 0, report.log[-3000:]
    assert report.outputs_for_invalid == 0, report.table()
    assert report.missing_outputs == 0 and report.wrong_outputs == 0, report.table()
    assert report.canary_changed == 0
    # every message accounted for by the node itself
    t = report.totals
    assert t["received"] == report.messages, report.table()
    assert t["published"] == report.valid_sent and t["failed"] == 0
    assert t["invalid"] + t["dropped_stale"] == report.invalid_sent
    assert report.superseded <= max(2, report.invalid_sent // 20)
    # every malformed kind named in a warning, and warnings throttled (5 s per problem kind)
    assert report.warned_kinds_missing == []
    distinct_problem_kinds = 20
    assert report.warnings <= distinct_problem_kinds * (report.duration_s / 5.0 + 1)
    assert report.warnings < report.invalid_sent
    # memory: the 2M cloud's buffers stay with the allocator, but nothing grows per message
    assert report.rss_after_mb - report.rss_before_mb < 250, report.table()
    assert report.messages_after_last_big >= 20
    assert report.rss_after_mb - report.rss_after_last_big_mb < 15, report.table()
