"""User factor plugins: factor types added through the configuration, without editing fgslam.

A run's ``factors`` section lists plugins::

    factors:
      - class: fgslam.services.plugins:PositionPrior      # "package.module:ClassName"
        options: {file: gps.txt, sigma: 1.0}
      - class: my_package.my_factors:WheelOdometry
        options: {...}

Each class is imported by its dotted path and built as ``Cls(options: dict, key: str)`` where ``key``
is its config key (``"factors[0]"``): the plugin validates its own options and names bad ones as
``factors[0].options.<name>`` (:func:`fgslam.contracts.plugins.parse_options` does that for a typed options dataclass). Loading
a config builds each plugin once to check it (:func:`validate_factor_entries`) and the run builds it
again, so a constructor only validates (files are read when the run starts: ``check_run``/``attach``). It
must have ``attach(backend)``, called once when the run's :class:`~fgslam.backend.graph.Backend`
exists: a plugin typically registers ``backend.on_keyframe(callback)`` (``callback(kf_id, timestamp,
key)`` after each new keyframe) and adds GTSAM factors with ``backend.add_factor(factor, owner=key)``
(an :class:`~fgslam.core.errors.OptimizationError` naming the key when a factor uses a key the backend
does not hold). Optional methods: ``check_run(timestamps)`` (the run's frame times, before the first
frame: refuse data that cannot apply), ``poll(backend)`` (the safe point after every frame, where a
plugin may move the map: on_keyframe callbacks run inside a frontend's frame) and
``finish(backend)`` (after the last frame).

A plugin moves the map with :func:`apply_correction` (a ``PoseCorrection``, as loop closure does):
through the backend's correction route (its ``contributors``, which :class:`FactorPlugins` sets to the
run's frontend before the plugins attach: each contributor moves its keyframes and folds the scale
into its structure); without one by setting every keyframe pose, scales included (nothing to fold
into). :func:`can_fold` says which; the corrections themselves are built with
:mod:`fgslam.services.corrections` (``uniform_correction``, ``pose_graph_correction``).

Two built-in plugins:

- :class:`PositionPrior`: GPS-like positions from a file (``t x y z`` per line). It brings a
  monocular map into the positions' metric frame (one Sim(3) Umeyama alignment once the samples
  spread enough, applied as a uniform pose correction that the frontends fold into their
  structure), then puts a position prior on every keyframe that has a sample within ``max_dt``
  and runs a Sim(3) pose-graph correction every ``correct_every`` new priors and at the end.
- :class:`PlanarMotion`: a ground vehicle's camera keeps its height above the ground plane and its
  roll/pitch across it (a plane fitted to the keyframes, see :mod:`fgslam.factors.planar`).
"""

from __future__ import annotations

import bisect
import dataclasses
import importlib
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Optional, Union

import numpy as np

from ..core.config import MAX_COUNT, MAX_KEYFRAMES, MAX_SCALAR, MAX_TIME_OFFSET_S, ranged
from ..contracts.contributor import PoseCorrection
from ..contracts.plugins import FactorPlugin, parse_options
from ..core.errors import ConfigError, FGSlamError
from ..factors.planar import fit_plane, planar_factor, plane_in_keyframe, plane_in_world, plane_of_keyframe, unit_up
from ..factors.position import camera_centre, position_noise, position_prior_factor
from ..core.geometry import umeyama
from ..io.positions import PositionTrack, read_positions
from .corrections import pose_graph_correction, route_correction, takes_corrections, uniform_correction

if TYPE_CHECKING:  # the backend pulls torch and gtsam: annotations only (a run's config checks the plugins without them)
    from ..backend.graph import Backend

logger = logging.getLogger(__name__)


FACTORS_KEY = "factors"  # the SlamConfig section
ENTRY_KEYS = ("class", "options")


# ----------------------------------------------------------------------------------------- loading


def plugin_key(index: int) -> str:
    """Config key of the ``index``-th plugin entry: ``factors[index]``."""
    return f"{FACTORS_KEY}[{index}]"


#: plugin modules of earlier releases -> where they are now (a config naming the old one gets told)
MOVED_MODULES = {"fgslam.backend.plugins": "fgslam.services.plugins"}


def load_plugin_class(spec: object, key: str) -> type[FactorPlugin]:
    """The class named by ``spec`` (``"package.module:ClassName"``); ConfigError naming ``<key>.class``
    when it is malformed, does not import, names no class there, or the class lacks ``attach``."""
    where = f"{key}.class"
    if not isinstance(spec, str) or spec.count(":") != 1 or not all(spec.split(":")):
        raise ConfigError(f"{where}: expected 'package.module:ClassName', got {spec!r}")
    module_name, class_name = spec.split(":")
    if module_name in MOVED_MODULES:
        raise ConfigError(f"{where}: module '{module_name}' moved to '{MOVED_MODULES[module_name]}' "
                          f"(write '{MOVED_MODULES[module_name]}:{class_name}')")
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # noqa: BLE001 - any failure while importing user code is reported with the key
        raise ConfigError(f"{where}: module '{module_name}' does not import: {type(exc).__name__}: {exc}") from exc
    cls = module
    for part in class_name.split("."):
        cls = getattr(cls, part, None)
        if cls is None:
            raise ConfigError(f"{where}: module '{module_name}' has no class '{class_name}'")
    if not isinstance(cls, type):
        raise ConfigError(f"{where}: '{spec}' is not a class ({type(cls).__name__})")
    if not callable(getattr(cls, "attach", None)):
        raise ConfigError(f"{where}: class '{spec}' lacks the method attach(backend) that a factor plugin needs")
    return cls


def build_plugin(entry: object, index: int) -> FactorPlugin:
    """Build the plugin of one ``factors`` entry (``{class: ..., options: {...}}``); errors name the key."""
    key = plugin_key(index)
    if not isinstance(entry, Mapping):
        raise ConfigError(f"{key}: expected a mapping with keys 'class' and 'options', got {entry!r}")
    unknown = sorted(str(k) for k in entry if k not in ENTRY_KEYS)
    if unknown:
        raise ConfigError(f"{key}: unknown key '{key}.{unknown[0]}' (valid keys: {', '.join(ENTRY_KEYS)})")
    if "class" not in entry:
        raise ConfigError(f"{key}.class: missing (the plugin's 'package.module:ClassName')")
    options = entry.get("options") or {}
    if not isinstance(options, Mapping):
        raise ConfigError(f"{key}.options: expected a mapping of option names to values, got {options!r}")
    cls = load_plugin_class(entry["class"], key)
    try:
        return cls(dict(options), key)
    except FGSlamError:
        raise
    except Exception as exc:  # noqa: BLE001 - a user plugin's constructor failing is a config problem of that entry
        raise ConfigError(f"{key}: building {entry['class']} failed: {type(exc).__name__}: {exc}") from exc


def build_plugins(entries: Sequence[object]) -> list[FactorPlugin]:
    """Build every plugin of a ``factors`` list, in order (see :func:`build_plugin`)."""
    return [build_plugin(entry, i) for i, entry in enumerate(entries)]


def attach_plugins(plugins: Sequence[FactorPlugin], backend: Backend, timestamps: Optional[np.ndarray] = None) -> None:
    """Before the first frame: ``check_run(timestamps)`` (when the plugin has it and times are given),
    then ``attach(backend)``, for each plugin (their corrections take the backend's route, its
    ``contributors``: set it first)."""
    for plugin in plugins:
        check = getattr(plugin, "check_run", None)  # optional members of a user plugin
        if timestamps is not None and callable(check):
            check(np.asarray(timestamps, dtype=np.float64))
        plugin.attach(backend)


def poll_plugins(plugins: Sequence[FactorPlugin], backend: Backend) -> None:
    """At the frontend's safe point after each frame: ``poll(backend)`` of each plugin that has it."""
    for plugin in plugins:
        poll = getattr(plugin, "poll", None)
        if callable(poll):
            poll(backend)


def finish_plugins(plugins: Sequence[FactorPlugin], backend: Backend) -> None:
    """After the last frame: ``finish(backend)`` of each plugin that has it."""
    for plugin in plugins:
        finish = getattr(plugin, "finish", None)
        if callable(finish):
            finish(backend)


# ----------------------------------------------------------------------------------------- corrections


def can_fold(backend: Backend) -> bool:
    """Whether the backend's corrections reach contributors that fold their scale into structure (its
    route, ``backend.contributors``; else a correction moves the keyframe poses with their scales: a
    Sim(3) map stays consistent without folding)."""
    return bool(backend.contributors)


def apply_correction(backend: Backend, correction: PoseCorrection) -> None:
    """Move the map by a pose correction (``fgslam.loop.records.PoseCorrection``: a Sim(3) update per
    keyframe) along the backend's route: each of ``backend.contributors`` moves its keyframes and folds
    the scale into its structure; without contributors each keyframe pose is set (build such
    corrections with ``fold_scale`` = :func:`can_fold`, False)."""
    route_correction(backend, correction, backend.contributors)


class FactorPlugins:
    """The run's factor plugins (a ``factors`` list), a service of the run's system: built and attached
    to ``backend`` before the first frame (``check_run(timestamps)`` first), :meth:`poll` after each
    frame (the safe point: no optimisation running) and :meth:`finish` after the last. It sets the
    backend's correction route to ``contributor`` (the frontend, when it takes corrections), so the
    plugins' corrections reach it before its final trajectory is read."""

    def __init__(self, entries: Sequence[object], backend: Backend, timestamps: Optional[np.ndarray] = None,
                 contributor: object = None) -> None:
        self.plugins = build_plugins(entries)
        self.backend = backend
        backend.set_contributors([contributor] if takes_corrections(contributor) else [])
        attach_plugins(self.plugins, backend, timestamps)

    def poll(self) -> None:
        poll_plugins(self.plugins, self.backend)

    def finish(self) -> None:
        finish_plugins(self.plugins, self.backend)


# ----------------------------------------------------------------------------------------- PositionPrior


@dataclasses.dataclass
class PositionPriorOptions:
    """Options of :class:`PositionPrior` (``factors[i].options``)."""

    file: Optional[Path] = None  # positions file, 't x y z' per line (seconds on the dataset's clock, metres); required
    sigma: Union[float, list[float]] = ranged(1.0, gt=0, le=MAX_SCALAR)  # metres: one (isotropic) or a list of three (x, y, z)
    time_offset: float = ranged(0.0, ge=-MAX_TIME_OFFSET_S, le=MAX_TIME_OFFSET_S)  # seconds added to the file's times to put them on the dataset's clock
    max_dt: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # s: a sample becomes a prior on the keyframe nearest in time when that close
    huber_k: Optional[float] = ranged(None, gt=0, le=MAX_SCALAR)  # whitened Huber threshold against outlier fixes (null: Gaussian)
    min_samples: int = ranged(10, ge=3, le=MAX_COUNT)  # samples matched to keyframes before the map is aligned to the positions
    min_spread: float = ranged(20.0, gt=0, le=MAX_SCALAR)  # m: largest principal standard deviation of those samples before aligning
    # m: second principal standard deviation before aligning: a straight path leaves the rotation about it open
    min_lateral_spread: float = ranged(3.0, ge=0, le=MAX_SCALAR)
    correct_every: int = ranged(10, ge=0, le=MAX_KEYFRAMES)  # a pose-graph correction after every this many new priors (0: only at the end)
    align_scale: bool = True  # the alignment estimates the map's scale (monocular); false: rigid (stereo, RGB-D maps)


class PositionPrior:
    """GPS-like position priors that pin the scale and drift of a (monocular) map.

    Samples of the positions file are matched to keyframes as they arrive: each sample goes to the
    keyframe nearest in time when within ``max_dt`` (a keyframe keeps the nearest sample), its
    position interpolated linearly at the keyframe's time. Until the map is aligned, these pairs are
    only collected; once ``min_samples`` of them spread ``min_spread`` (and ``min_lateral_spread``
    across the main direction), the Sim(3) Umeyama alignment of the keyframe centres onto the
    positions moves the whole map into the positions' frame (one uniform correction), and from then
    on every matched keyframe gets a position-prior factor (``owner`` = this plugin's key) and a
    Sim(3) pose-graph correction (``backend.correct_pose_graph``) runs after every ``correct_every``
    new priors and at :meth:`finish`.
    """

    def __init__(self, options: Mapping[str, object], key: str) -> None:
        self.key = key
        self.options = opts = parse_options(PositionPriorOptions, options, key)
        if opts.file is None:
            raise ConfigError(f"{key}.options.file: missing (the positions file, 't x y z' per line)")
        if isinstance(opts.sigma, list) and len(opts.sigma) != 3:
            raise ConfigError(f"{key}.options.sigma: expected one sigma or a list of three (x, y, z), got {opts.sigma}")
        self.sigma = opts.sigma
        position_noise(self.sigma, opts.huber_k)  # the noise model is valid (ranges checked above)
        self._track: Optional[PositionTrack] = None  # read when the run starts (check_run / attach)
        self.backend: Optional[Backend] = None
        self._kf_times: list[float] = []  # keyframes in arrival order
        self._kf_ids: list[int] = []
        self._kf_keys: dict[int, int] = {}
        self._next_sample = 0  # first sample not yet matched to a keyframe
        self._matched: dict[int, tuple[float, np.ndarray, int]] = {}  # kf_id -> (|dt|, position, sample index)
        self._handles: dict[int, int] = {}  # kf_id -> factor handle
        self._since_correction = 0
        self.alignment: Optional[np.ndarray] = None  # the 4x4 Sim(3) applied, once aligned
        self.corrections = 0

    @property
    def aligned(self) -> bool:
        return self.alignment is not None

    @property
    def track(self) -> PositionTrack:
        """The positions file (read on first use: a config names it, the run reads it)."""
        if self._track is None:
            self._track = read_positions(self.options.file)
        return self._track

    @property
    def times(self) -> np.ndarray:
        """Sample times on the dataset's clock (file times + ``time_offset``)."""
        return self.track.t + self.options.time_offset

    # -- plugin interface
    def check_run(self, timestamps: np.ndarray) -> None:
        """DataError naming the file and lines when no sample lies within the run's frame times."""
        if timestamps.size:
            self.track.check_overlap(float(timestamps[0]) - self.options.time_offset,
                                     float(timestamps[-1]) - self.options.time_offset)

    def attach(self, backend: Backend) -> None:
        self._times = self.times
        self.backend = backend
        backend.on_keyframe(self._on_keyframe)

    def finish(self, backend: Backend) -> None:
        self._match_samples(math.inf)
        self._rematch()
        if not self.aligned:
            self._try_align()
        if self.aligned:
            self._add_priors()
            self.correct()
        if not self.aligned:
            logger.warning("%s: the map was never aligned to the positions (%d samples matched to keyframes; "
                           "options min_samples %d, min_spread %g m, min_lateral_spread %g m): no position priors",
                           self.key, len(self._matched), self.options.min_samples, self.options.min_spread,
                           self.options.min_lateral_spread)
            return
        logger.info("%s: %d position priors, %d pose-graph corrections", self.key, len(self._handles), self.corrections)

    def poll(self, backend: Backend) -> None:
        """Safe point (after a frame, no optimisation running): align the map once the samples allow
        it, then a pose-graph correction after every ``correct_every`` new priors."""
        self._rematch()
        if self.aligned:
            self._add_priors()
        if not self.aligned:
            self._try_align()
        elif self.options.correct_every and self._since_correction >= self.options.correct_every:
            self.correct()

    # -- matching samples to keyframes
    def _on_keyframe(self, kf_id: int, timestamp: float, key: int) -> None:
        """Inside the backend's add_keyframe (a frontend mid-frame): only match samples and add priors;
        anything that moves the map waits for :meth:`poll`."""
        i = bisect.bisect_right(self._kf_times, float(timestamp))  # kept in time order
        self._kf_times.insert(i, float(timestamp))
        self._kf_ids.insert(i, int(kf_id))
        self._kf_keys[int(kf_id)] = int(key)
        self._match_samples(float(timestamp))
        if self.aligned:
            self._add_priors()

    def _match_samples(self, t_now: float) -> None:
        """Match every sample up to ``t_now`` (the keyframes around it are known) to a keyframe."""
        while self._next_sample < len(self._times) and self._times[self._next_sample] <= t_now:
            self._next_sample += 1
            self._assign(self._next_sample - 1)

    def _assign(self, j: int) -> None:
        """Give sample ``j`` to the keyframe in the backend nearest to it in time, when within ``max_dt``
        and that keyframe has no nearer sample (a nearer sample replaces its prior)."""
        t_s, max_dt = self._times[j], self.options.max_dt
        lo, hi = bisect.bisect_left(self._kf_times, t_s - max_dt), bisect.bisect_right(self._kf_times, t_s + max_dt)
        best = None
        for i in range(lo, hi):
            if self.backend.has_keyframe(self._kf_ids[i]) and (best is None or abs(self._kf_times[i] - t_s) < best[0]):
                best = (abs(self._kf_times[i] - t_s), i)
        if best is None:
            return
        dt, i = best
        kf_id = self._kf_ids[i]
        if kf_id in self._matched and self._matched[kf_id][0] <= dt:
            return
        if kf_id in self._handles:
            self.backend.remove_factor(self._handles.pop(kf_id))
        self._matched[kf_id] = (dt, self.track.interpolate(self._kf_times[i] - self.options.time_offset), j)

    def _rematch(self) -> None:
        """Samples of keyframes the backend dropped (a frontend removing redundant keyframes) go to the
        nearest remaining keyframe (their factors went with the keyframe)."""
        for kf_id in [k for k in self._matched if not self.backend.has_keyframe(k)]:
            _, _, j = self._matched.pop(kf_id)
            self._handles.pop(kf_id, None)
            self._assign(j)

    # -- alignment, priors, corrections
    def _pairs(self) -> tuple[list[int], np.ndarray, np.ndarray]:
        ids = [k for k in self._matched if self.backend.has_keyframe(k)]
        centres = np.array([camera_centre(self.backend.pose(k)) for k in ids]).reshape(-1, 3)
        positions = np.array([self._matched[k][1] for k in ids]).reshape(-1, 3)
        return ids, centres, positions

    def _try_align(self) -> bool:
        ids, centres, positions = self._pairs()
        if len(ids) < self.options.min_samples:
            return False
        spread = np.linalg.svd(positions - positions.mean(axis=0), compute_uv=False) / math.sqrt(len(ids))
        if spread[0] < self.options.min_spread or spread[1] < self.options.min_lateral_spread:
            return False
        if np.linalg.svd(centres - centres.mean(axis=0), compute_uv=False)[0] <= 0:
            return False
        a = umeyama(centres, positions, with_scale=self.options.align_scale)
        U = np.eye(4)
        U[:3, :3] = a.s * a.R
        U[:3, 3] = a.t
        rms_before = float(np.sqrt(np.mean(np.sum((centres - positions) ** 2, axis=1))))
        apply_correction(self.backend, uniform_correction(self.backend, U, can_fold(self.backend)))
        self.alignment = U
        # from here the position priors fix the map's pose and scale: the anchor and range gauge
        # factors (at the map's own, now moved, first keyframes) would fight them
        self.backend.set_gauge(anchor=None, scale_pair=None)
        aligned = np.array([camera_centre(self.backend.pose(k)) for k in ids])
        rms = float(np.sqrt(np.mean(np.sum((aligned - positions) ** 2, axis=1))))
        logger.info("%s: map aligned to the positions on %d samples (scale %.4f; rms %.3f -> %.3f m)",
                    self.key, len(ids), a.s, rms_before, rms)
        self._add_priors()
        self.correct()
        return True

    def _add_priors(self) -> None:
        for kf_id, (_, p, _) in self._matched.items():
            if kf_id in self._handles or not self.backend.has_keyframe(kf_id):
                continue
            factor = position_prior_factor(self._kf_keys[kf_id], p, self.sigma, self.options.huber_k)
            self._handles[kf_id] = self.backend.add_factor(factor, owner=self.key)
            self._since_correction += 1

    def correct(self) -> None:
        """Sim(3) pose-graph correction over every keyframe (odometry from the current estimate and the
        persistent factors, these priors among them), applied as a per-keyframe correction."""
        if not self._handles:
            return
        T_WC_new = self.backend.correct_pose_graph()
        apply_correction(self.backend, pose_graph_correction(self.backend, T_WC_new, can_fold(self.backend)))
        self._since_correction = 0
        self.corrections += 1


# ----------------------------------------------------------------------------------------- PlanarMotion


@dataclasses.dataclass
class PlanarMotionOptions:
    """Options of :class:`PlanarMotion` (``factors[i].options``)."""

    # the ground normal in camera coordinates (the camera's up axis): (0, -1, 0) for a level
    # forward-looking camera with y down; include the mount's pitch and roll (calibrated)
    up_axis: list[float] = ranged(default_factory=lambda: [0.0, -1.0, 0.0], ge=-MAX_SCALAR, le=MAX_SCALAR)  # finite; not all zero (checked)
    height_sigma: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # world units (metres in a metric map): camera height above the plane
    tilt_sigma: float = ranged(0.01, gt=0, le=MAX_SCALAR)  # rad (sine of the angle): roll and pitch across the plane
    refit_every: int = ranged(10, ge=1, le=MAX_KEYFRAMES)  # new keyframes between two fits of the plane to every keyframe
    refit_tolerance: float = ranged(0.1, gt=0, le=MAX_SCALAR)  # rebuild the factors when a fit moves the plane by more than this many sigmas
    # a Sim(3) pose-graph correction over every keyframe at the end, then a last fit: only where other
    # factors hold the scale (PositionPrior): alone, the pose graph's free scale shrinks the map to lower
    # the height residuals (street drive: ATE 2.7 -> 10.8 m)
    correct_at_finish: bool = False


class PlanarMotion:
    """Planar-motion constraint for ground vehicles: every keyframe's camera stays on the camera plane
    (the plane parallel to the ground in which the camera centre moves) with its ``up_axis`` along the
    plane's normal, through :func:`fgslam.factors.planar.planar_factor` (``owner`` = this plugin's key).

    The plane is held in the coordinates of a reference keyframe (the first one; when the backend
    drops it, the oldest remaining one), so that corrections moving the whole map (a position
    alignment, a loop closure) move it too. It starts as the first keyframe's plane; every
    ``refit_every`` keyframes the plugin fits it to all keyframes
    (:func:`fgslam.factors.planar.fit_plane`, which averages out the attitude and height wobble of
    single keyframes) and rebuilds the factors when the fit moved it by more than ``refit_tolerance``
    sigmas. At :meth:`finish`: a last fit and, with ``correct_at_finish``, a Sim(3) pose-graph
    correction over every keyframe and another fit.

    Without gravity the plane's attitude in the map is known only through the keyframes' attitudes
    (the first keyframe's wobble included), so a map may lie on a slightly tilted plane: the
    constraint fixes each camera's height and tilt relative to that plane, not the map's tilt in an
    outside frame."""

    def __init__(self, options: Mapping[str, object], key: str) -> None:
        self.key = key
        self.options = parse_options(PlanarMotionOptions, options, key)
        try:
            self.up_C = unit_up(self.options.up_axis)
        except ValueError as exc:
            raise ConfigError(f"{key}.options.up_axis: {exc} (the ground normal in camera coordinates)") from exc
        self.backend: Optional[Backend] = None
        self.reference: Optional[int] = None  # keyframe whose coordinates hold the plane
        self.plane_C: Optional[tuple[np.ndarray, float]] = None  # (n, d): n . x + d = 0 in the reference camera
        self._plane_W: Optional[tuple[np.ndarray, float]] = None  # the plane in the world at the last (re)build
        self._keys: dict[int, int] = {}
        self._handles: dict[int, int] = {}
        self._since_fit = 0
        self.rebuilds = 0

    def attach(self, backend: Backend) -> None:
        self.backend = backend
        backend.on_keyframe(self._on_keyframe)

    @property
    def plane(self) -> Optional[tuple[np.ndarray, float]]:
        """The camera plane ``(n_W, d_W)`` in the world at the reference keyframe's current pose."""
        if self.plane_C is None or not self.backend.has_keyframe(self.reference):
            return self._plane_W
        return plane_in_world(self.backend.pose(self.reference), *self.plane_C)

    def finish(self, backend: Backend) -> None:
        self.refit()
        if self.options.correct_at_finish and self._handles:
            apply_correction(backend, pose_graph_correction(backend, backend.correct_pose_graph(), can_fold(backend)))
            self.refit()
        plane = self.plane
        logger.info("%s: %d planar factors, plane normal %s offset %.3f, %d rebuilds", self.key,
                    len(self._handles), None if plane is None else np.round(plane[0], 4),
                    math.nan if plane is None else plane[1], self.rebuilds)

    def _on_keyframe(self, kf_id: int, timestamp: float, key: int) -> None:
        self._keys[int(kf_id)] = int(key)
        if self.plane_C is None:
            self._rebuild(int(kf_id), plane_of_keyframe(self.backend.pose(kf_id), self.up_C))
        elif not self.backend.has_keyframe(self.reference):
            self._rebuild(self._oldest(), self._plane_W)
        else:
            self._add(int(kf_id))
        self._since_fit += 1
        if self._since_fit >= self.options.refit_every:
            self.refit()

    def _oldest(self) -> int:
        return min(k for k in self._keys if self.backend.has_keyframe(k))

    def _add(self, kf_id: int) -> None:
        if kf_id == self.reference or kf_id in self._handles:
            return
        n, d = self.plane_C
        factor = planar_factor(self._keys[self.reference], self._keys[kf_id], n, d, self.up_C,
                               self.options.height_sigma, self.options.tilt_sigma)
        self._handles[kf_id] = self.backend.add_factor(factor, owner=self.key)

    def _rebuild(self, reference: int, plane_W: tuple[np.ndarray, float]) -> None:
        """Hold the world plane ``plane_W`` in keyframe ``reference``'s coordinates; rebuild every factor."""
        present = set(self.backend.factor_handles(self.key))
        for handle in self._handles.values():
            if handle in present:
                self.backend.remove_factor(handle)
        self._handles.clear()
        self._keys = {k: v for k, v in self._keys.items() if self.backend.has_keyframe(k)}
        if self.reference is not None and reference != self.reference:
            logger.info("%s: keyframe %d holds the plane (keyframe %d left the backend)", self.key, reference,
                        self.reference)
        self.reference = reference
        self._plane_W = plane_W
        self.plane_C = plane_in_keyframe(self.backend.pose(reference), *plane_W)
        for k in self._keys:
            self._add(k)

    def refit(self) -> None:
        """Fit the plane to every keyframe's current pose; rebuild the factors when it moved."""
        self._since_fit = 0
        alive = [k for k in self._keys if self.backend.has_keyframe(k)]
        if len(alive) < 2:
            return
        poses = [self.backend.pose(k) for k in alive]
        centres = np.array([camera_centre(T) for T in poses])
        rotations = np.array([T.rotation().matrix() for T in poses])
        n, d = fit_plane(centres, rotations, self.up_C, self.options.height_sigma, self.options.tilt_sigma)
        n_old, d_old = self.plane
        angle = float(np.arccos(np.clip(n @ n_old, -1.0, 1.0)))
        shift = float(np.max(np.abs(centres @ (n - n_old) + (d - d_old))))
        tol = self.options.refit_tolerance
        if angle <= tol * self.options.tilt_sigma and shift <= tol * self.options.height_sigma:
            return
        reference = self.reference if self.backend.has_keyframe(self.reference) else min(alive)
        self._rebuild(reference, (n, d))
        self.rebuilds += 1


# ----------------------------------------------------------------------------------------- config validation


def validate_factor_entries(entries: object) -> None:
    """Check a ``factors`` list before any work: each entry's class imports and has ``attach`` and
    its plugin accepts the options (built once and dropped; errors name ``factors[i]...``)."""
    if not isinstance(entries, (list, tuple)):
        raise ConfigError(f"{FACTORS_KEY}: expected a list of {{class, options}} entries, got {entries!r}")
    build_plugins(entries)
