"""Never a silent wrong pose: a pose's trust follows the chain it was tracked from
(slam.tracking.acceptance's trust along the chain, through the pipeline).

A wrong relocalisation is made on purpose (the first relocalisation's registrations moved by 4 mm
after they passed their checks, as a registration onto the wrong place would be): the frames tracked from it
inherit the wrong pose, and the map, once it covers the view again, pulls the track back (a snap
back). Each of those is flagged; no trusted frame errs by more than 1 mm against the last trusted
frame before it (silent frames along the chain, slam.evaluation.chain)."""
from __future__ import annotations

import numpy as np
import pytest

from slam.app.pipeline import Pipeline
from slam.config import load_config
from slam.evaluation.chain import chain_errors, silent_summary
from slam.io.datasets import open_dataset
from slam.tracking.state import TRUST
from tests.conftest import copy_with

GAP = range(40, 45)          # five unreadable frames: the frame after them is relocalised before it is tracked
WRONG_MM = 4.0


@pytest.fixture(scope="module")
def scanning(tmp_path_factory):
    from slam.synth import generate

    return generate(tmp_path_factory.mktemp("trust") / "scan", "scanning", frames=90, size=(320, 256), seed=5)


def _wrong_registration(monkeypatch):
    """The first relocalisation's registrations moved sideways by ``WRONG_MM`` once verified."""
    from slam.tracking.recovery import FrameRelocaliser

    register, relocalise = FrameRelocaliser.register, FrameRelocaliser.relocalise
    calls = []

    def wrong(self, view, cand, start):
        reg, plane_mm, why_not = register(self, view, cand, start)
        if len(calls) == 1:
            moved = np.eye(4)
            moved[0, 3] = WRONG_MM
            reg.relative = reg.relative @ moved
        return reg, plane_mm, why_not

    def counted(self, *args, **kwargs):
        calls.append(1)
        return relocalise(self, *args, **kwargs)

    monkeypatch.setattr(FrameRelocaliser, "register", wrong)
    monkeypatch.setattr(FrameRelocaliser, "relocalise", counted)


def _run(data, out):
    cfg = load_config(None, ["tracking.mode=frame2model", "threads=1"])
    pipe = Pipeline(cfg, open_dataset(data, cfg.data), out)
    result = pipe.run(progress=False)
    records = result.records
    return (pipe, result, records, np.stack([r.pose for r in records]), np.array([r.failed for r in records]),
            np.array([r.flagged for r in records]))


def test_a_wrong_relocalisation_its_inherited_poses_and_the_snap_back_are_flagged(scanning, tmp_path, monkeypatch):
    """The frames after the wrong relocalisation carry its error and are flagged, the track snaps
    back onto the map where it refutes the chain (flagged), the snap's correction repairs the
    stretch, and no trusted frame is silently wrong. Before the trust chain the frames after it were
    tracked against the previous frame or kept the last frame's estimate, and a rebuild of the map
    around the view made the wrong pose the map's: frames 4 mm off, unflagged, to the end."""
    _wrong_registration(monkeypatch)
    data = copy_with(scanning, tmp_path / "gap", GAP, lambda path: path.write_bytes(b"lost"))
    pipe, result, records, poses, failed, flagged = _run(data, tmp_path / "run")
    truth = pipe.dataset.gt_poses
    after = GAP.stop
    assert records[after].reference == "relocalised" and records[after].flagged
    # the relocalised pose is wrong by about the 4 mm it was moved
    position_error = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    before = position_error[GAP.start - 1]
    assert position_error[after] - before > 2.0
    # every pose that carries it is flagged, and the track jumps back onto the map (flagged too)
    wrong = np.flatnonzero(position_error - before > 2.0)
    assert (flagged | failed)[wrong].all(), [(k, records[k].trust) for k in wrong if not flagged[k]]
    jumps = np.flatnonzero(chain_errors(poses, truth, np.ones(len(records), bool)) > 2.0)
    assert len(jumps) >= 2 and flagged[jumps[jumps > after]].all()      # (the relocalisation, the snap back)
    # no trusted frame is silently wrong along the chain; the track is right again after the snap back
    summary = silent_summary(poses, truth, flagged, failed)
    assert summary["silent_over"] == 0, summary
    assert (position_error[after + 5:] - before < 0.5).all()
    # what each pose rests on is written and counted
    trust = np.array([r.trust for r in records])
    assert set(trust) <= set(TRUST) and trust[0] == "confirmed"
    assert (trust[list(GAP)] == "failed").all() and (trust[after + 5:] == "confirmed").all()
    assert sum(result.metrics["trust"].values()) == len(records)
    assert result.metrics["trust"]["confirmed"] == (trust == "confirmed").sum()
    csv = (tmp_path / "run" / "tracking.csv").read_text().splitlines()
    assert csv[0].split(",")[4] == "trust" and csv[after + 1].split(",")[4] == "flagged"
    # the map's correction at the snap back repairs the stretch before it: trajectory.txt holds the
    # corrected poses, trajectory_online.txt those known at the time, metrics.json both ATEs
    from slam.io.tum import read_tum

    _, online = read_tum(tmp_path / "run" / "trajectory_online.txt")
    _, final = read_tum(tmp_path / "run" / "trajectory.txt")
    np.testing.assert_allclose(online, poses, atol=1e-5)
    assert result.metrics["repaired_frames"] >= 1
    repaired = np.flatnonzero(np.abs(final - online).max(axis=(1, 2)) > 1e-4)
    assert after in repaired and all(flagged[k] for k in repaired)
    assert np.linalg.norm(final[after, :3, 3] - truth[after, :3, 3]) - before < 1.0
    assert result.metrics["ate_rmse_mm"] < result.metrics["online"]["ate_rmse_mm"]


def test_a_stretch_is_corrected_linearly_from_the_last_held_pose():
    """Drift along four unconfirmed frames (0.1 mm a frame), ended by the map at frame 5 with the
    chain 0.5 mm off: each frame takes its share; a stretch that begins with a relocalisation
    takes the correction whole; a re-anchoring ends a stretch without one."""
    from slam.tracking.chain_repair import ChainRepair
    from slam.tracking.state import FrameResult

    def pose(x):
        T = np.eye(4)
        T[0, 3] = x
        return T

    repair = ChainRepair()
    repair.follow(0, pose(0.0), FrameResult(pose(0.0), trust="confirmed"))
    for k in range(1, 5):
        repair.follow(k, pose(k + 0.1 * k), FrameResult(pose(0), trust="unconfirmed", flagged=True))
    end = FrameResult(pose(5.0), trust="confirmed", map_correction=pose(-0.5))
    assert repair.follow(5, pose(5.0), end) == [1, 2, 3, 4]
    for k in range(1, 5):
        assert repair.corrections[k][0, 3] == pytest.approx(k + 0.1 * k - 0.5 * k / 5)
    # a relocalisation's error is the stretch's own: every frame after it carries it whole
    repair.follow(6, pose(9.0), FrameResult(pose(0), trust="flagged", flagged=True, reference="relocalised"))
    repair.follow(7, pose(10.0), FrameResult(pose(0), trust="unconfirmed", flagged=True))
    repair.follow(8, pose(7.0), FrameResult(pose(0), trust="flagged", flagged=True, snapped_to_map=True,
                                            map_correction=pose(-3.0)))
    assert repair.corrections[6][0, 3] == pytest.approx(6.0) and repair.corrections[7][0, 3] == pytest.approx(7.0)
    # a re-anchoring: the new map was built from the chain, the stretch before it stays as tracked
    repair.follow(9, pose(8.5), FrameResult(pose(0), trust="unconfirmed", flagged=True))
    repair.follow(10, pose(9.5), FrameResult(pose(0), trust="unconfirmed", flagged=True, anchors_map=True))
    assert repair.follow(11, pose(10.0), FrameResult(pose(0), trust="confirmed", map_correction=pose(1.0))) == []
    assert 9 not in repair.corrections and repair.repairs == 2
    tracked = np.stack([pose(float(k)) for k in range(12)])
    corrected = repair.corrected(tracked)
    assert corrected[6][0, 3] == pytest.approx(6.0) and corrected[9][0, 3] == pytest.approx(9.0)
    assert ChainRepair().corrected(tracked) is None
