"""The dense frontend's bundle adjustment through the backend: edges measured from the field the current
estimate induces, one :class:`~fgslam.factors.dense.DenseBlock` over them, the local BA of the newest
keyframes (step 3 of :mod:`.frontend`) and the global optimisation of the map (step 5: its snapshot,
solve and hand-over; :mod:`.contributor` runs it)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from functools import partial
from typing import Optional

import numpy as np

from ...backend.config import BackendConfig
from ...backend.keys import pose_key
from ...backend.snapshot import SnapshotProblem, optimize_snapshot
from ...factors.dense import DenseBlock, DenseEdge, DenseKeyframe
from ...factors.reprojection import ReprojectionConfig
from ...factors.schur import torch_threads
from ...contracts.contributor import GlobalBAJob
from ..records import rigid
from .config import DenseConfig, DenseProximityConfig
from .graph import DenseKeyframeState, EdgeMeasurement, FrameGraph, select_global_edges
from .source import make_dense_source
from .state import DenseState
from .weights import block_config, huber_weight, information

logger = logging.getLogger(__name__)


def measure_edges(g: FrameGraph, source, config: DenseConfig, stride: int, edges: list[tuple[int, int]],
                  min_change: float = 0.0) -> int:
    """Measure ``edges`` of graph ``g`` with ``source`` from the fields the current estimate induces;
    stores their revisions (confidence times the Huber weight of the revision) and the sources'
    confidence maps. ``min_change`` (image px, > 0): an edge whose induced field moved less than this
    on average since its last measurement keeps that measurement (the flow would start where it
    started). Returns the number of edges that kept theirs."""
    if not edges:
        return 0
    induced, _ = g.induced(edges)
    kept = 0
    if min_change > 0:
        moved = g.induced_change(edges, induced) * stride >= min_change
        kept = int((~moved).sum())
        edges = [e for e, m in zip(edges, moved) if m]
        induced = induced[moved]
    revs = source.revise(edges, induced) if edges else []
    for (i, j), rev, ind in zip(edges, revs, induced):
        w = rev.weight * huber_weight(rev.target - ind, config, stride)
        # the induced field is kept only for the local BA's comparison (cleared when the edge leaves the active graph)
        g.edges[(i, j)] = EdgeMeasurement(rev.target, w, ind.astype(np.float32) if min_change > 0 else None)
    for i in sorted({e[0] for e in edges}):
        kf = g.keyframes[i]
        kf.confidence = np.max([g.edges[e].weight.mean(-1) for e in g.edges if e[0] == i], axis=0)
    return kept


def dense_block(g: FrameGraph, edges: list[tuple[int, int]], K_grid, config: DenseConfig, stride: int,
                reprojection: ReprojectionConfig, extra: list[tuple[tuple[int, int], EdgeMeasurement]] = ()) -> DenseBlock:
    """One dense block over the measured ``edges`` of ``g`` and the ``extra`` measurements (loop edges),
    their sources' inverse depths eliminated."""
    info = information(config, stride)
    measured = [(e, g.edges[e]) for e in edges] + list(extra)
    order = {f: k for k, f in enumerate(g.keyframes)}
    sources = sorted({e[0] for e, _ in measured}, key=order.__getitem__)
    kfs = [DenseKeyframe(pose_key(i), g.keyframes[i].inv_depth, sensor_depth=g.keyframes[i].sensor_depth,
                         stereo=g.keyframes[i].stereo) for i in sources]
    dedges = [DenseEdge(pose_key(i), pose_key(j), m.target, m.weight * info) for (i, j), m in measured]
    return DenseBlock(kfs, dedges, K_grid, block_config(config, reprojection))


class DenseBA:
    """Measurement and optimisation of the keyframes of the shared ``state`` (its graph, source, backend,
    counts and stage times); ``name`` owns the dense blocks on the backend."""

    def __init__(self, state: DenseState, name: str):
        self.state = state
        self.name = name
        self.depth_name = f"{name}.depth"  # the owner of the depth-alignment blocks (RGB-D)

    def measure(self, edges: list[tuple[int, int]], min_change: float = 0.0) -> None:
        """Measure ``edges`` from the fields the current estimate induces (:func:`measure_edges`; an edge
        whose field moved less than ``min_change`` image px since its last measurement keeps it)."""
        if not edges:
            return
        st = self.state
        t0 = time.perf_counter()
        st.counts["edges_kept"] += measure_edges(st.graph, st.source, st.config, st.stride, edges, min_change)
        st.times["flow"] += time.perf_counter() - t0

    def block(self, edges: list[tuple[int, int]]) -> DenseBlock:
        """One dense block over the measured ``edges`` (:func:`dense_block`)."""
        st = self.state
        return dense_block(st.graph, edges, st.K_grid, st.config, st.stride, st.reproj)

    def optimize(self, free: list[int], edges: list[tuple[int, int]], iterations: int, init: bool) -> None:
        """One optimisation of the free keyframes with the dense block of ``edges`` through the backend
        (the local BA and the initialisation; the global optimisation is :func:`solve_dense_global`)."""
        st = self.state
        g = st.graph
        block = self.block(edges)
        free_keys = {pose_key(f) for f in free}
        depth_blocks = self.depth_blocks(free_keys, False)
        keys = set(block.keys).union(*(b.keys for b in depth_blocks))
        fixed = [k for k in keys if k not in free_keys]
        anchor = free[0] if (init or not fixed) else None
        pair = (free[0], free[-1]) if init and st.sensor_mode == "mono" and len(free) >= 2 else None
        st.backend.set_gauge(anchor=anchor, scale_pair=pair)
        st.backend.set_blocks(self.name, [block])
        if st.depth.enabled:
            st.backend.set_blocks(self.depth_name, depth_blocks)
        st.backend.optimize_window(free, iterations)
        fid_of = {pose_key(f): f for f in g.keyframes}
        for src in block.sources:
            g.keyframes[fid_of[src.keys[0]]].inv_depth = src.inverse_depth.numpy().copy()
        if st.sensor_mode == "rgbd":  # sensor depths observe no Sim(3) scale: written back rigid (as patch)
            st.backend.write_back_rigid(free)

    def depth_blocks(self, free_keys: set[int], global_: bool) -> list:
        """RGB-D depth alignment: the depth blocks between consecutive keyframes of the map (with their
        surfaces) at least one of which is free; the newest ``depth_align.window_pairs`` of them, every one
        in the global optimisation. Empty when depth alignment is off."""
        st = self.state
        if not st.depth.enabled:
            return []
        g = st.graph
        frames = [(pose_key(f), g.keyframes[f].surface) for f in g.order()]
        return st.depth.chain(frames, free_keys, 0 if global_ else None)

    def local(self, new_fid: int, rounds: int | None = None) -> None:
        """Local BA after keyframe ``new_fid``: ``rounds`` (default ``ba.rounds``) of re-measuring the
        newest keyframes' edges and optimising the newest ``ba.window`` keyframes."""
        st = self.state
        t0 = time.perf_counter()
        g = st.graph
        cfg = st.config.ba
        free = g.active[-cfg.window:]
        free_set = set(free)
        edges = [e for e in g.active_edges() if e[0] in free_set or e[1] in free_set]
        newest = set(g.active[-cfg.remeasure:]) | {new_fid}
        fresh = [e for e in edges if e[0] in newest or e[1] in newest]
        flow0 = st.times["flow"]
        for _ in range(cfg.rounds if rounds is None else rounds):
            self.measure(fresh, cfg.remeasure_min_change)
            self.optimize(free, edges, cfg.iterations, init=False)
        st.times["ba"] += time.perf_counter() - t0 - (st.times["flow"] - flow0)

    def clear_blocks(self) -> None:
        """Take this map's blocks (dense, and RGB-D depth alignment's) off the backend (a map restart)."""
        st = self.state
        st.backend.set_blocks(self.name, [])
        if st.depth.enabled:
            st.backend.set_blocks(self.depth_name, [])

    # ------------------------------------------------------------------ global optimisation
    @property
    def jobs_in_process(self) -> bool:
        """Whether global jobs run in the loop service's worker process: the built-in flow source without
        RGB-D depth alignment (a learned source, or depth blocks the caller builds, keep them in a thread)."""
        return self.state.config.source.kind == "flow" and not self.state.depth.enabled

    def global_job(self, loop_edges: dict | None = None) -> GlobalBAJob | None:
        """Snapshot of the current map for a global optimisation (None: fewer than three keyframes with
        images): every keyframe's pose and inverse depths, the images of those that keep theirs (the
        N x N flow distances, the edge selection and the measurement run in the job: :func:`solve_dense_global`),
        the stored edges of the others, the loop edges kept so far and ``loop_edges`` (measured). A source
        other than the built-in flow measures here, in the caller; the job then runs in a thread (as with
        RGB-D depth alignment, whose blocks the caller builds), else in the loop service's worker process."""
        st = self.state
        g = st.graph
        if g is None:
            return None
        kf_ids = g.order()
        imaged = [f for f in kf_ids if g.keyframes[f].image is not None]
        if len(imaged) < 3:
            return None
        imaged_set = set(imaged)
        stored = {e: m for e, m in g.edges.items() if not (e[0] in imaged_set and e[1] in imaged_set)}
        st.loop_edges = {e for e in st.loop_edges if e[0] in g.keyframes and e[1] in g.keyframes}
        extra = sorted(e for e in st.loop_edges if e[0] in imaged_set and e[1] in imaged_set)
        measured = None
        images = {f: st.cropped(g.keyframes[f].image) for f in imaged}
        in_process = self.jobs_in_process
        if st.config.source.kind != "flow":  # the learned source stays in this process: measured here
            edges = global_edges(g, imaged, st.config)
            chosen = set(edges)
            edges += [e for e in extra if e not in chosen]
            held = set(g.edges)
            self.measure(edges)
            measured = {e: g.edges[e] for e in edges}
            for e in edges:  # the graph keeps only the edges it had (the hand-over adds those it lacks)
                if e not in held:
                    del g.edges[e]
            images = {}
        T_WC = np.stack([st.backend.pose_matrix(f) for f in kf_ids])
        inv_depth = [g.keyframes[f].inv_depth for f in kf_ids]
        settings = DenseGlobalSettings(config=st.config, backend=st.backend.config, K_grid=np.asarray(st.K_grid),
                                       shape=g.shape, stride=st.stride, reprojection=st.reproj,
                                       mono=st.sensor_mode == "mono", rigid=st.sensor_mode == "rgbd",
                                       proximity=st.config.proximity)
        loop = None
        if loop_edges is not None and len(loop_edges["src"]):
            loop = {k: np.asarray(v) for k, v in loop_edges.items()}
        depth_blocks = self.depth_blocks({pose_key(f) for f in kf_ids}, True)
        snapshot = DenseGlobalSnapshot(
            settings=settings, kf_ids=list(kf_ids), T_WC=T_WC.copy(),
            timestamps=[float(g.keyframes[f].timestamp) for f in kf_ids], inv_depth=[d.copy() for d in inv_depth],
            sensor_depth=[g.keyframes[f].sensor_depth for f in kf_ids], stereo=[g.keyframes[f].stereo for f in kf_ids],
            images=images, stored=stored, extra=extra, loop=loop, measured=measured, depth_blocks=depth_blocks)
        n_loop = 0 if loop is None else len(loop["src"])
        return GlobalBAJob(solve=partial(solve_dense_global, snapshot), kf_ids=np.asarray(kf_ids, np.int64), T_WC=T_WC,
                           is_loop=np.ones(n_loop, bool), loop_edges=loop, in_process=in_process,
                           delay_frames=int(np.ceil(st.config.global_ba.delay_frames_per_keyframe * len(kf_ids))),
                           context={"inv_depth": inv_depth})

    def apply_global(self, job: GlobalBAJob, result: "DenseGlobalResult", keep_loop: np.ndarray) -> None:
        """Hand-over of an accepted global optimisation, before its pose correction: the optimised
        inverse depths (and confidences) of the keyframes whose pose and depths did not change since the
        snapshot (the others keep theirs: their pose gets the correction, their depths are the newer
        local BA's); the measured edges between active keyframes that the graph lacks (or whose
        keyframes did not change) join it; the loop edges that kept a weight join it and every later
        global optimisation."""
        st = self.state
        g = st.graph
        if g is None:
            return
        unchanged = set()
        for k, fid in enumerate(int(f) for f in job.kf_ids):
            kf = g.keyframes.get(fid)
            if kf is None or not st.backend.has_keyframe(fid):
                continue
            if np.array_equal(st.backend.pose_matrix(fid), job.T_WC[k]) and np.array_equal(kf.inv_depth, job.context["inv_depth"][k]):
                unchanged.add(fid)
                kf.inv_depth = result.inv_depth[k]
                if fid in result.confidence:
                    kf.confidence = result.confidence[fid]
        active = set(g.active)
        for e, m in result.measured.items():
            if e[0] in active and e[1] in active and (e not in g.edges or (e[0] in unchanged and e[1] in unchanged)):
                g.edges[e] = m
        loop = job.loop_edges
        for n in np.nonzero(np.asarray(keep_loop, bool))[0]:
            e = (int(loop["src"][n]), int(loop["tgt"][n]))
            if e[0] in g.keyframes and e[1] in g.keyframes:
                st.loop_edges.add(e)
                g.edges.setdefault(e, EdgeMeasurement(loop["target"][n], loop["weight"][n]))
        st.counts["global_runs"] += 1


def global_edges(g: FrameGraph, fids: list[int], config: DenseConfig) -> list[tuple[int, int]]:
    """The global optimisation's edges among keyframes ``fids`` (in order): DROID-SLAM's selection
    (:func:`.graph.select_global_edges`) from their N x N flow-distance matrix."""
    cfg = config.global_ba
    n = len(fids)
    pairs = [(a, b) for a in fids for b in fids if a != b]
    dist = np.full((n, n), np.inf)
    d = g.flow_distance(pairs, config.graph.distance_stride)
    index = {f: k for k, f in enumerate(fids)}
    for (a, b), v in zip(pairs, d):
        dist[index[a], index[b]] = v
    return select_global_edges(fids, dist, cfg.temporal_radius, cfg.nms_radius, cfg.max_distance, cfg.max_edges)


@dataclass
class DenseGlobalSettings:
    """What a global optimisation job needs of the frontend (plain, picklable data)."""

    config: DenseConfig
    backend: BackendConfig  # the run backend's ``map`` section (the snapshot's scratch backend)
    K_grid: np.ndarray
    shape: tuple[int, int]  # (h, w) of the grid
    stride: int
    reprojection: ReprojectionConfig
    mono: bool  # monocular: the first two keyframes carry the world scale
    rigid: bool  # RGB-D: poses written back rigid (sensor depths observe no Sim(3) scale)
    proximity: Optional[DenseProximityConfig] = None  # the loop edges' inlier test


@dataclass
class DenseGlobalSnapshot:
    """A global optimisation's input (:meth:`DenseBA.global_job`): keyframes ``kf_ids`` of the map in
    order with their poses, inverse depths, sensor depths and stereo rows; ``images`` the cropped grey
    images of those that keep theirs; ``stored`` the last measurements of the edges not among them;
    ``extra`` edges measured besides the selected ones (loop edges kept earlier); ``loop`` the new loop
    edges (``src``, ``tgt`` (L,), ``target``, ``weight`` (L, h, w, 2)) or None; ``measured`` the edges
    the caller measured already (a source that cannot run in the worker; None: measured in the job);
    ``depth_blocks`` RGB-D depth alignment's blocks over the map."""

    settings: DenseGlobalSettings
    kf_ids: list[int]
    T_WC: np.ndarray
    timestamps: list[float]
    inv_depth: list[np.ndarray]
    sensor_depth: list
    stereo: list
    images: dict
    stored: dict
    extra: list
    loop: Optional[dict]
    measured: Optional[dict]
    depth_blocks: list


@dataclass
class DenseGlobalResult:
    """A solved :class:`DenseGlobalSnapshot`: poses ``T_WC`` (K, 4, 4) and inverse depths of its
    keyframes, the confidence maps of the measured sources, the measured edges, ``robust`` (L,) per
    loop edge (its inlier share, 0 when below ``proximity.min_edge_inliers``), ``num_edges``."""

    T_WC: np.ndarray
    inv_depth: list
    confidence: dict
    measured: dict
    robust: np.ndarray
    num_edges: int


def solve_dense_global(snapshot: DenseGlobalSnapshot) -> DenseGlobalResult:
    """Solve a global optimisation snapshot (in the loop service's worker, or at once): the edges
    selected from the N x N flow distances and measured with a source of the same config (unless the
    caller measured them), then ``global_ba.rounds`` rounds of one dense block over them, the stored
    edges and the loop edges, every keyframe free (the first one held; monocular: the distance to the
    second is the world scale), solved by the backend (:func:`fgslam.backend.snapshot.optimize_snapshot`)."""
    st = snapshot.settings
    cfg = st.config
    kf_ids = list(snapshot.kf_ids)
    poses = {f: np.asarray(T, np.float64) for f, T in zip(kf_ids, snapshot.T_WC)}
    g = FrameGraph(st.K_grid, st.shape, st.stride, st.reprojection, poses.__getitem__)
    for k, fid in enumerate(kf_ids):
        g.add(DenseKeyframeState(fid=fid, index=-1, timestamp=snapshot.timestamps[k], image=snapshot.images.get(fid),
                                 inv_depth=np.array(snapshot.inv_depth[k], np.float64, copy=True),
                                 colour=np.zeros((0, 0, 3), np.uint8), sensor_depth=snapshot.sensor_depth[k],
                                 stereo=snapshot.stereo[k], confidence=np.zeros(st.shape)))
    with torch_threads(cfg.threads):
        source = None
        if snapshot.measured is None:
            edges = global_edges(g, [f for f in kf_ids if f in snapshot.images], cfg)
            chosen = set(edges)
            edges += [e for e in snapshot.extra if e not in chosen]
            source = make_dense_source(cfg.source)
            for f in sorted({f for e in edges for f in e}):
                source.add_frame(f, snapshot.images[f])
        else:
            edges = list(snapshot.measured)
            g.edges.update(snapshot.measured)
        g.edges.update(snapshot.stored)
        loop = snapshot.loop
        loop_pairs = [] if loop is None else [(int(a), int(b)) for a, b in zip(loop["src"], loop["tgt"])]
        extra = [] if loop is None else [(e, EdgeMeasurement(loop["target"][n], loop["weight"][n]))
                                         for n, e in enumerate(loop_pairs)]
        measured_set = set(edges)
        blocks_on = list(edges) + [e for e in snapshot.stored if e not in measured_set]
        for _ in range(cfg.global_ba.rounds):
            if source is not None:
                measure_edges(g, source, cfg, st.stride, edges)
            block = dense_block(g, blocks_on, st.K_grid, cfg, st.stride, st.reprojection, extra)
            blocks = {"dense": [block]}
            if snapshot.depth_blocks:
                blocks["dense.depth"] = snapshot.depth_blocks
            problem = SnapshotProblem(st.backend, kf_ids, np.stack([poses[f] for f in kf_ids]), snapshot.timestamps,
                                      blocks, kf_ids, cfg.global_ba.iterations, anchor=kf_ids[0],
                                      scale_pair=(kf_ids[0], kf_ids[1]) if st.mono else None)
            T_new = optimize_snapshot(problem)
            fid_of = {pose_key(f): f for f in kf_ids}
            for src in block.sources:
                g.keyframes[fid_of[src.keys[0]]].inv_depth = src.inverse_depth.numpy().copy()
            for f, T in zip(kf_ids, T_new):
                poses[f] = rigid(T) if st.rigid else T
        robust = loop_inlier_shares(g, loop_pairs, [m for _, m in extra], st) if loop_pairs else np.zeros(0)
    measured_sources = {e[0] for e in edges}
    return DenseGlobalResult(T_WC=np.stack([poses[f] for f in kf_ids]), inv_depth=[g.keyframes[f].inv_depth for f in kf_ids],
                             confidence={f: g.keyframes[f].confidence for f in kf_ids if f in measured_sources},
                             measured={e: g.edges[e] for e in edges}, robust=robust, num_edges=len(blocks_on) + len(extra))


def loop_inlier_shares(g: FrameGraph, pairs: list[tuple[int, int]], measurements: list[EdgeMeasurement],
                       settings: DenseGlobalSettings) -> np.ndarray:
    """Per loop edge, the share of its weighted grid pixels whose residual (target minus the field the
    estimate induces) is below ``proximity.outlier_px`` image px; 0 where that share is below
    ``proximity.min_edge_inliers`` (the edge lost its weight)."""
    pc = settings.proximity
    induced, _ = g.induced(pairs)
    out = np.zeros(len(pairs))
    for n, (m, ind) in enumerate(zip(measurements, induced)):
        valid = (m.weight.mean(-1) > 0) & np.isfinite(ind).all(-1) & np.isfinite(m.target).all(-1)
        if not valid.any():
            continue
        r = np.linalg.norm(np.where(valid[..., None], m.target - ind, 0.0), axis=-1) * settings.stride
        share = float((r[valid] <= pc.outlier_px).mean())
        out[n] = share if share >= pc.min_edge_inliers else 0.0
    return out
