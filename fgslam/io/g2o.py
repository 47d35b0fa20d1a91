"""Reader and writer for g2o pose-graph files (2-D ``SE2`` and 3-D ``SE3:QUAT``).

Supported lines (whitespace separated; ``#`` starts a comment line; blank lines are skipped)::

    VERTEX_SE2       id x y theta
    EDGE_SE2         i j x y theta  I11 I12 I13 I22 I23 I33
    VERTEX_SE3:QUAT  id x y z qx qy qz qw
    EDGE_SE3:QUAT    i j x y z qx qy qz qw  <21 entries of the 6x6 upper triangle, row by row>
    FIX              id [id ...]

Conventions (those of g2o):

* A vertex value is the pose ``T_W_i`` of vertex ``i`` in the world frame; an edge measurement is
  the relative pose ``T_i_j = T_W_i^-1 T_W_j`` (vertex ``j`` expressed in the frame of vertex ``i``).
* 2-D poses are stored as ``[x, y, theta]``; 3-D poses as ``[x, y, z, qx, qy, qz, qw]`` (Hamilton
  unit quaternion, scalar last; normalised on reading).
* The information matrix is in g2o's tangent order: ``[x, y, theta]`` in 2-D and
  ``[x, y, z, rx, ry, rz]`` (translation first) in 3-D. Consumers with another tangent order
  (gtsam's Pose3 is rotation first) permute it themselves.

Some published files (e.g. the KITTI and Manhattan benchmarks of SE-Sync) contain only edges: then
``poses`` is ``None`` and the vertex ids are those the edges use. When a file has vertex lines, every
edge must join two declared vertices. Any deviation raises :class:`~fgslam.core.errors.FormatError`
naming the file and the line.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import DataError, FormatError

#: Tag -> (dimension, number of tokens on the line including the tag).
_VERTEX_TAGS = {"VERTEX_SE2": (2, 5), "VERTEX_SE3:QUAT": (3, 9)}
_EDGE_TAGS = {"EDGE_SE2": (2, 12), "EDGE_SE3:QUAT": (3, 31)}
_FIX_TAG = "FIX"

#: Parameters of a pose (and of a measurement) per dimension: [x, y, theta] or [x, y, z, qx, qy, qz, qw].
POSE_SIZE = {2: 3, 3: 7}
#: Tangent dimension per pose dimension (size of the information matrix).
TANGENT_DIM = {2: 3, 3: 6}

#: Quaternions whose norm is below this are not rotations (a fact of the representation, not a tuning).
_MIN_QUATERNION_NORM = 1e-12


@dataclass
class PoseGraph:
    """A pose graph as read from a g2o file.

    Attributes:
        dim: 2 (SE(2)) or 3 (SE(3)).
        ids: (N,) int64 vertex ids in file order (edge order of first use when there are no vertex lines).
        poses: (N, 3) ``[x, y, theta]`` or (N, 7) ``[x, y, z, qx, qy, qz, qw]`` poses ``T_W_i``, row k for
            ``ids[k]``; ``None`` when the file has no vertex lines.
        edges: (M, 2) int64 ``(i, j)`` vertex ids of each edge.
        measurements: (M, 3) or (M, 7) relative poses ``T_i_j`` in the same parameterisation as ``poses``.
        information: (M, 3, 3) or (M, 6, 6) symmetric positive-definite information matrices in g2o's
            tangent order (translation first).
        fixed: ids named on FIX lines, in file order.
        edge_lines: (M,) int64 line number of each edge in ``source`` (0 for graphs built in memory).
        indefinite_edges: (K,) int64 indices of edges whose information matrix is not positive definite
            (always empty unless the file was read with ``require_positive_definite=False``).
        source: file the graph was read from (for messages), or a description.
    """

    dim: int
    ids: np.ndarray
    poses: np.ndarray | None
    edges: np.ndarray
    measurements: np.ndarray
    information: np.ndarray
    fixed: list[int] = field(default_factory=list)
    edge_lines: np.ndarray | None = None
    indefinite_edges: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    source: str = "<memory>"

    def __post_init__(self) -> None:
        if self.edge_lines is None:
            self.edge_lines = np.zeros(self.edges.shape[0], dtype=np.int64)

    @property
    def num_vertices(self) -> int:
        return int(self.ids.shape[0])

    @property
    def num_edges(self) -> int:
        return int(self.edges.shape[0])


def _numbers(rows: list[list[str]], lines: list[int], path: Path) -> np.ndarray:
    """(K, n) float64 array of the tokens; FormatError naming the first bad line otherwise."""
    try:
        values = np.array(rows, dtype=np.float64)
    except ValueError:
        for row, lineno in zip(rows, lines):
            for tok in row:
                try:
                    float(tok)
                except ValueError:
                    raise FormatError(f"{path}:{lineno}: non-numeric value '{tok}'") from None
        raise  # unreachable: some token failed above
    finite = np.isfinite(values)
    if not finite.all():
        k, c = np.argwhere(~finite)[0]
        raise FormatError(f"{path}:{lines[k]}: non-finite value '{rows[k][c]}'")
    return values


def _ids(rows: list[list[str]], lines: list[int], path: Path) -> np.ndarray:
    """(K, n) int64 array of vertex ids; FormatError naming the first bad line otherwise."""
    try:
        return np.array([[int(tok) for tok in row] for row in rows], dtype=np.int64)
    except ValueError:
        for row, lineno in zip(rows, lines):
            for tok in row:
                try:
                    int(tok)
                except ValueError:
                    raise FormatError(f"{path}:{lineno}: vertex id '{tok}' is not an integer") from None
        raise  # unreachable: some token failed above


def _normalise_quaternions(q: np.ndarray, lines: list[int], path: Path) -> np.ndarray:
    """Rows of (K, 4) divided by their norms; FormatError for a zero quaternion."""
    norms = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~(norms > _MIN_QUATERNION_NORM))
    if bad.size:
        raise FormatError(f"{path}:{lines[bad[0]]}: quaternion has zero norm")
    return q / norms[:, None]


def _upper_triangles_to_matrices(values: np.ndarray, n: int) -> np.ndarray:
    """(K, n(n+1)/2) row-major upper triangles -> (K, n, n) symmetric matrices."""
    M = np.zeros((values.shape[0], n, n))
    rows, cols = np.triu_indices(n)
    M[:, rows, cols] = values
    M[:, cols, rows] = values
    return M


def _indefinite_indices(information: np.ndarray) -> np.ndarray:
    """Indices of the (K, n, n) symmetric matrices that are not positive definite (Cholesky fails)."""
    try:
        np.linalg.cholesky(information)  # batched: fast path when all are positive definite
        return np.zeros(0, dtype=np.int64)
    except np.linalg.LinAlgError:
        pass
    bad = [k for k, M in enumerate(information) if not _is_positive_definite(M)]
    return np.array(bad, dtype=np.int64)


def _is_positive_definite(M: np.ndarray) -> bool:
    try:
        np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        return False
    return True


def read_g2o(path: str | Path, require_positive_definite: bool = True) -> PoseGraph:
    """Read a 2-D or 3-D g2o pose graph (see the module docstring for the format and conventions).

    With ``require_positive_definite=False`` an edge whose information matrix is not positive definite
    is kept as written and its index listed in ``PoseGraph.indefinite_edges`` (some published files,
    e.g. ``cubicle``, contain such matrices); the caller decides what to do with it.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise FormatError(f"{path}: cannot read g2o file: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise FormatError(f"{path}: not a text file ({exc.reason})") from exc

    # Pass 1: check tags, token counts and dimension per line; keep the tokens.
    dim: int | None = None
    dim_line = 0
    vertex_rows: list[list[str]] = []
    vertex_lines: list[int] = []
    edge_rows: list[list[str]] = []
    edge_lines: list[int] = []
    fix_rows: list[tuple[str, int]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        tag = tokens[0]
        if tag == _FIX_TAG:
            if len(tokens) < 2:
                raise FormatError(f"{path}:{lineno}: FIX needs at least one vertex id")
            fix_rows.extend((tok, lineno) for tok in tokens[1:])
            continue
        if tag in _VERTEX_TAGS:
            line_dim, n_tokens = _VERTEX_TAGS[tag]
            rows, lines = vertex_rows, vertex_lines
        elif tag in _EDGE_TAGS:
            line_dim, n_tokens = _EDGE_TAGS[tag]
            rows, lines = edge_rows, edge_lines
        else:
            raise FormatError(f"{path}:{lineno}: unknown tag '{tag}'")
        if len(tokens) != n_tokens:
            raise FormatError(
                f"{path}:{lineno}: {tag} needs {n_tokens - 1} values after the tag, found {len(tokens) - 1}"
            )
        if dim is None:
            dim, dim_line = line_dim, lineno
        elif dim != line_dim:
            raise FormatError(f"{path}:{lineno}: {tag} is {line_dim}-D but line {dim_line} made this a {dim}-D graph")
        rows.append(tokens[1:])
        lines.append(lineno)
    if dim is None:
        raise FormatError(f"{path}: no vertices or edges found (empty g2o file?)")
    n_pose, n_tan = POSE_SIZE[dim], TANGENT_DIM[dim]

    # Pass 2: convert in bulk; errors still name the first offending line.
    edges = _ids([row[:2] for row in edge_rows], edge_lines, path).reshape(-1, 2)
    loops = np.flatnonzero(edges[:, 0] == edges[:, 1])
    if loops.size:
        raise FormatError(f"{path}:{edge_lines[loops[0]]}: edge joins vertex {edges[loops[0], 0]} to itself")
    n_values = n_pose + n_tan * (n_tan + 1) // 2
    edge_values = _numbers([row[2:] for row in edge_rows], edge_lines, path).reshape(-1, n_values)
    measurements = edge_values[:, :n_pose].copy()
    if dim == 3:
        measurements[:, 3:] = _normalise_quaternions(measurements[:, 3:], edge_lines, path)
    information = _upper_triangles_to_matrices(edge_values[:, n_pose:], n_tan)

    poses: np.ndarray | None = None
    if vertex_rows:
        ids = _ids([row[:1] for row in vertex_rows], vertex_lines, path)[:, 0]
        poses = _numbers([row[1:] for row in vertex_rows], vertex_lines, path)
        if dim == 3:
            poses[:, 3:] = _normalise_quaternions(poses[:, 3:], vertex_lines, path)
        first_line: dict[int, int] = {}
        for vid, lineno in zip(ids.tolist(), vertex_lines):
            if vid in first_line:
                raise FormatError(f"{path}:{lineno}: vertex {vid} already defined on line {first_line[vid]}")
            first_line[vid] = lineno
        missing = ~np.isin(edges, ids)
        if missing.any():
            k, c = np.argwhere(missing)[0]
            raise FormatError(
                f"{path}:{edge_lines[k]}: edge refers to vertex {edges[k, c]}, which the file does not define"
            )
    else:
        ids = np.array(list(dict.fromkeys(edges.ravel().tolist())), dtype=np.int64)

    fixed_ids = _ids([[tok] for tok, _ in fix_rows], [ln for _, ln in fix_rows], path).ravel().tolist()
    known = set(ids.tolist())
    for vid, (_, lineno) in zip(fixed_ids, fix_rows):
        if vid not in known:
            raise FormatError(f"{path}:{lineno}: FIX names vertex {vid}, which is not in the graph")

    indefinite = _indefinite_indices(information)
    if indefinite.size and require_positive_definite:
        raise FormatError(f"{path}:{edge_lines[int(indefinite[0])]}: information matrix is not positive definite")
    return PoseGraph(
        dim=dim,
        ids=ids,
        poses=poses,
        edges=edges,
        measurements=measurements,
        information=information,
        fixed=fixed_ids,
        edge_lines=np.array(edge_lines, dtype=np.int64),
        indefinite_edges=indefinite,
        source=str(path),
    )


def write_g2o(path: str | Path, graph: PoseGraph) -> None:
    """Write ``graph`` in g2o format (full float64 precision, so that reading it back is exact)."""
    path = Path(path)
    if graph.dim not in POSE_SIZE:
        raise DataError(f"{path}: cannot write a {graph.dim}-D pose graph (only 2-D and 3-D)")
    vertex_tag = "VERTEX_SE2" if graph.dim == 2 else "VERTEX_SE3:QUAT"
    edge_tag = "EDGE_SE2" if graph.dim == 2 else "EDGE_SE3:QUAT"
    n_tan = TANGENT_DIM[graph.dim]
    rows, cols = np.triu_indices(n_tan)

    def fmt(values: np.ndarray) -> str:
        return " ".join(repr(float(v)) for v in values)

    lines = []
    if graph.poses is not None:
        for vid, pose in zip(graph.ids.tolist(), graph.poses):
            lines.append(f"{vertex_tag} {vid} {fmt(pose)}")
    for (i, j), meas, info in zip(graph.edges.tolist(), graph.measurements, graph.information):
        lines.append(f"{edge_tag} {i} {j} {fmt(meas)} {fmt(info[rows, cols])}")
    if graph.fixed:
        lines.append(f"{_FIX_TAG} " + " ".join(str(v) for v in graph.fixed))
    try:
        path.write_text("\n".join(lines) + "\n")
    except OSError as exc:
        raise DataError(f"{path}: cannot write g2o file: {exc.strerror or exc}") from exc
