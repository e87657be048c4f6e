"""The daemon's estimates log (CSV of every estimate, TUM of the sent ones): content, paths, failures."""

from __future__ import annotations

import numpy as np
import pytest

from companion.geometry import rot_from_rpy
from companion.io.estimate_log import CSV_HEADER, EstimateLog, log_paths
from companion.types import EstimateStatus, PoseEstimate


def estimate(t_us: int, p, rpy, status: EstimateStatus = EstimateStatus.OK) -> PoseEstimate:
    cov = np.diag([0.04, 0.09, 0.16, 1e-4, 4e-4, 9e-4])
    return PoseEstimate(
        t_us, np.asarray(p, float), np.asarray(rpy, float), cov, reset_counter=2, quality=0.8, status=status
    )


def test_every_estimate_in_the_csv_the_sent_ones_in_the_tum(tmp_path) -> None:
    log = EstimateLog(str(tmp_path / "run" / "est.csv"))
    log.write(estimate(1_700_000_000_000_000, [1.0, 2.0, -30.0], [0.01, -0.02, 1.2]), "sent")
    log.write(estimate(1_700_000_000_066_667, [1.1, 2.1, -30.0], [0.01, -0.02, 1.2]), "rate_cap")
    log.write(
        estimate(1_700_000_000_133_333, [np.nan] * 3, [0.0, 0.0, 0.0], EstimateStatus.LOST), "status_lost"
    )
    log.close()
    rows = (tmp_path / "run" / "est.csv").read_text().splitlines()
    assert rows[0] == CSV_HEADER and len(rows) == 4
    first = rows[1].split(",")
    assert float(first[0]) == pytest.approx(1_700_000_000.0)
    assert [float(v) for v in first[1:4]] == [1.0, 2.0, -30.0]
    assert [float(v) for v in first[7:13]] == pytest.approx([0.2, 0.3, 0.4, 0.01, 0.02, 0.03])
    assert first[14:] == ["ok", "sent", "2"]
    assert rows[2].split(",")[15] == "rate_cap" and rows[3].split(",")[14:16] == ["lost", "status_lost"]
    tum = np.loadtxt(tmp_path / "run" / "est.tum", ndmin=2)
    assert tum.shape == (1, 8)
    # the quaternion (x y z w) is R_world_body of the roll / pitch / yaw sent
    x, y, z, w = tum[0, 4:]
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    assert np.allclose(R, rot_from_rpy(0.01, -0.02, 1.2), atol=1e-6)
    # a second run appends to the same files without a second header
    log = EstimateLog(str(tmp_path / "run" / "est"))
    log.write(estimate(1_700_000_001_000_000, [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]), "sent")
    log.close()
    rows = (tmp_path / "run" / "est.csv").read_text().splitlines()
    assert len(rows) == 5 and rows.count(CSV_HEADER) == 1


def test_paths_and_failures(tmp_path) -> None:
    csv, tum = log_paths(str(tmp_path / "flight-{time}.tum"), start_time_s=0.0)
    assert csv.suffix == ".csv" and tum.suffix == ".tum" and csv.stem == tum.stem
    assert "{time}" not in csv.name and csv.name.startswith("flight-19")
    # a path that cannot be created fails at start, with the OS's reason
    (tmp_path / "a_file").write_text("")
    with pytest.raises(OSError):
        EstimateLog(str(tmp_path / "a_file" / "est"))
    # a write that fails in flight is counted, never raised
    log = EstimateLog(str(tmp_path / "est"))
    log._csv.close()  # the storage went away under the daemon
    log.write(estimate(1, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), "sent")
    log.write(estimate(2, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]), "sent")
    assert log.status()["errors"] == 2 and log.status()["lines"] == 0
    log.close()
