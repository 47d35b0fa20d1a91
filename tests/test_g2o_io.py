"""Tests of the g2o reader/writer (fgslam/io/g2o.py) on small generated files."""

import subprocess
import sys

import numpy as np
import pytest

from fgslam.core.errors import FormatError
from fgslam.io.g2o import PoseGraph, read_g2o, write_g2o

GOOD_2D = """# a comment line
VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1.0 0.5 0.1

VERTEX_SE2 2 2.0 1.0 -0.2
EDGE_SE2 0 1 1.0 0.5 0.1 10 1 2 20 3 30
EDGE_SE2 1 2 1.1 0.4 -0.3 11 0 0 12 0 13
FIX 0
"""

GOOD_3D = """VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1
VERTEX_SE3:QUAT 5 1 2 3 0 0 0.6 0.8
# quaternion below is not unit length: the reader normalises it
VERTEX_SE3:QUAT 7 4 5 6 0 0 0 2
EDGE_SE3:QUAT 0 5 1 2 3 0 0 0.6 0.8 1 0 0 0 0 0 2 0 0 0 0 3 0 0 0 4 0 0 5 0 6
EDGE_SE3:QUAT 5 7 1 1 1 0.1 0.2 0.3 0.9 10 1 0 0 0 0 10 0 0 0 0 10 0 0 0 20 0 0 20 0 20
"""


def write_text(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_read_2d(tmp_path):
    g = read_g2o(write_text(tmp_path, "good2d.g2o", GOOD_2D))
    assert g.dim == 2
    assert g.ids.tolist() == [0, 1, 2]
    np.testing.assert_array_equal(g.poses[1], [1.0, 0.5, 0.1])
    assert g.edges.tolist() == [[0, 1], [1, 2]]
    np.testing.assert_array_equal(g.measurements[1], [1.1, 0.4, -0.3])
    np.testing.assert_array_equal(g.information[0], [[10, 1, 2], [1, 20, 3], [2, 3, 30]])
    assert g.fixed == [0]
    assert g.edge_lines.tolist() == [6, 7]
    assert g.indefinite_edges.size == 0


def test_read_3d_normalises_quaternions_and_unpacks_upper_triangle(tmp_path):
    g = read_g2o(write_text(tmp_path, "good3d.g2o", GOOD_3D))
    assert g.dim == 3
    assert g.ids.tolist() == [0, 5, 7]
    np.testing.assert_allclose(g.poses[2], [4, 5, 6, 0, 0, 0, 1])
    np.testing.assert_allclose(np.linalg.norm(g.measurements[:, 3:], axis=1), 1.0)
    np.testing.assert_array_equal(np.diag(g.information[0]), [1, 2, 3, 4, 5, 6])
    assert g.information[1][0, 1] == g.information[1][1, 0] == 1
    np.testing.assert_array_equal(g.information, np.transpose(g.information, (0, 2, 1)))


def test_edges_only_file_has_no_poses(tmp_path):
    g = read_g2o(write_text(tmp_path, "edges.g2o", "EDGE_SE2 3 4 1 0 0 1 0 0 1 0 1\nEDGE_SE2 4 9 1 0 0 1 0 0 1 0 1\n"))
    assert g.poses is None
    assert g.ids.tolist() == [3, 4, 9]


V2 = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
E2 = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"

MALFORMED = {
    "vertex_token_count": (V2 + "VERTEX_SE2 2 1 0\n", 3, "needs 4 values"),
    "edge_token_count": (V2 + "EDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", 3, "needs 11 values"),
    "edge3d_token_count": ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 0 0 0 0 0 0 0 1 1\n", 2, "30 values"),
    "non_numeric": (V2 + "EDGE_SE2 0 1 1 zero 0 1 0 0 1 0 1\n", 3, "non-numeric value 'zero'"),
    "non_finite": (V2 + "EDGE_SE2 0 1 1 nan 0 1 0 0 1 0 1\n", 3, "non-finite"),
    "non_integer_id": (V2 + "EDGE_SE2 0 1.5 1 0 0 1 0 0 1 0 1\n", 3, "not an integer"),
    "unknown_tag": ("# header\n" + V2 + "VERTEX_XY 2 1 1\n", 4, "unknown tag 'VERTEX_XY'"),
    "missing_vertex": (V2 + E2 + "EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n", 4, "vertex 2"),
    "not_positive_definite": (V2 + "EDGE_SE2 0 1 1 0 0 1 2 0 1 0 1\n", 3, "not positive definite"),
    "zero_information": (V2 + "EDGE_SE2 0 1 1 0 0 0 0 0 0 0 0\n", 3, "not positive definite"),
    "self_loop": (V2 + "EDGE_SE2 1 1 1 0 0 1 0 0 1 0 1\n", 3, "joins vertex 1 to itself"),
    "duplicate_vertex": (V2 + "VERTEX_SE2 1 2 0 0\n", 3, "already defined on line 2"),
    "mixed_dimensions": (V2 + "VERTEX_SE3:QUAT 2 0 0 0 0 0 0 1\n", 3, "3-D but line 1"),
    "zero_quaternion": ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0\n", 1, "zero norm"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_file_names_file_and_line(tmp_path, case):
    text, line, what = MALFORMED[case]
    path = write_text(tmp_path, f"bad_{case}.g2o", text)
    with pytest.raises(FormatError) as info:
        read_g2o(path)
    message = str(info.value)
    assert f"{path}:{line}:" in message
    assert what in message


@pytest.mark.parametrize("text", ["", "# only a comment\n\n"])
def test_empty_file(tmp_path, text):
    path = write_text(tmp_path, "empty.g2o", text)
    with pytest.raises(FormatError, match="no vertices or edges"):
        read_g2o(path)


def test_fix_of_unknown_vertex(tmp_path):
    path = write_text(tmp_path, "fix.g2o", V2 + E2 + "FIX 7\n")
    with pytest.raises(FormatError, match="FIX names vertex 7"):
        read_g2o(path)


def test_missing_file(tmp_path):
    with pytest.raises(FormatError, match="cannot read"):
        read_g2o(tmp_path / "nope.g2o")


def test_indefinite_information_kept_when_allowed(tmp_path):
    path = write_text(tmp_path, "indef.g2o", V2 + E2 + "EDGE_SE2 0 1 1 0 0 1 2 0 1 0 1\n")
    g = read_g2o(path, require_positive_definite=False)
    assert g.indefinite_edges.tolist() == [1]
    assert g.edge_lines.tolist() == [3, 4]


def random_graph(rng, dim, n, m):
    """Random pose graph with unit quaternions and random SPD information matrices."""
    n_tan = 3 if dim == 2 else 6

    def random_poses(k):
        if dim == 2:
            return np.column_stack([rng.normal(size=(k, 2)), rng.uniform(-np.pi, np.pi, k)])
        q = rng.normal(size=(k, 4))
        return np.column_stack([rng.normal(size=(k, 3)), q / np.linalg.norm(q, axis=1, keepdims=True)])

    A = rng.normal(size=(m, n_tan, n_tan))
    info = A @ np.transpose(A, (0, 2, 1)) + n_tan * np.eye(n_tan)
    first = rng.integers(0, n, m)
    second = (first + rng.integers(1, n, m)) % n  # never equal to first: no self-loops
    edges = np.column_stack([first, second]) + 100
    return PoseGraph(
        dim=dim,
        ids=np.arange(n, dtype=np.int64) + 100,
        poses=random_poses(n),
        edges=edges.astype(np.int64),
        measurements=random_poses(m),
        information=info,
        fixed=[100, 102],
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_write_read_roundtrip_is_exact(tmp_path, dim):
    rng = np.random.default_rng(dim)
    g = random_graph(rng, dim, n=20, m=40)
    path = tmp_path / f"rt{dim}.g2o"
    write_g2o(path, g)
    back = read_g2o(path)
    assert back.dim == dim
    np.testing.assert_array_equal(back.ids, g.ids)
    np.testing.assert_array_equal(back.edges, g.edges)
    np.testing.assert_array_equal(back.information, g.information)
    np.testing.assert_allclose(back.poses, g.poses, rtol=0, atol=1e-15)
    np.testing.assert_allclose(back.measurements, g.measurements, rtol=0, atol=1e-15)
    assert back.fixed == g.fixed


def test_information_matches_gtsam_reader(shared_data):
    """Our unpacking (g2o order [t, r]) agrees with gtsam.readG2o's Pose3 noise model ([r, t]) on a real file."""
    import gtsam

    path = shared_data / "g2o" / "smallGrid3D.g2o"
    g = read_g2o(path)
    fg, values = gtsam.readG2o(str(path), True)
    assert fg.size() == g.num_edges
    perm = [3, 4, 5, 0, 1, 2]
    for k in range(g.num_edges):
        factor = fg.at(k)
        assert list(factor.keys()) == g.edges[k].tolist()
        np.testing.assert_allclose(factor.noiseModel().information(), g.information[k][np.ix_(perm, perm)], rtol=1e-12)
        qx, qy, qz, qw = g.measurements[k, 3:]
        R_expected = gtsam.Rot3.Quaternion(qw, qx, qy, qz).matrix()
        np.testing.assert_allclose(factor.measured().rotation().matrix(), R_expected, atol=1e-12)
        np.testing.assert_allclose(factor.measured().translation(), g.measurements[k, :3], atol=1e-12)
    for vid, pose in zip(g.ids.tolist(), g.poses):
        np.testing.assert_allclose(values.atPose3(vid).translation(), pose[:3], atol=1e-12)


def test_io_module_imports_no_slam_or_gtsam():
    code = (
        "import sys, fgslam.io.g2o\n"
        "bad = [m for m in sys.modules if m == 'gtsam' or m == 'torch' or m.startswith(('fgslam.factors', "
        "'fgslam.frontends', 'fgslam.loop', 'fgslam.run.pgo'))]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
