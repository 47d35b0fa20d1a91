"""The root configuration of a run (``fgslam run``): :class:`SlamConfig` (presets:
``fgslam/configs/*.yaml``), its output section, and loading it from a preset or a file with
``key=value`` overrides."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, Optional

from ..backend.config import BackendConfig
from ..core.config import MAX_FRAMES, MAX_MEMORY_MIB, MAX_SCALAR, MAX_THREADS, load_config, ranged, with_sections
from ..eval.trajectory import EvalConfig
from ..export.mapfile import MapFeaturesConfig, MapJoinConfig, MapMergeConfig
from ..export.ply import PlyExportConfig
from ..export.rerun import RerunConfig
from ..frontends import FRONTEND_NAMES, family_config_classes
from ..io.datasets import DatasetConfig
from ..loop.records import LoopClosureConfig
from ..services.imu_samples import ImuServiceConfig
from ..services.plugins import validate_factor_entries
from .presets import resolve_preset


SensorName = Literal["mono", "stereo", "rgbd"]


@dataclass
class OutputConfig:
    """What a run writes besides trajectories and summary."""

    plot: bool = True  # write trajectory.png (top view of estimate vs ground truth)
    # plot plane; auto: the two axes of largest ground-truth (else estimate) extent
    plot_plane: Literal["auto", "xy", "xz", "yz"] = "auto"
    write_ply: bool = False  # write points.ply from the frontend's keyframe points (when it provides them)
    ply: PlyExportConfig = field(default_factory=PlyExportConfig)  # points.ply: far points left out by `fgslam export --ply`'s rule
    write_depth: bool = False  # write depth/<kf:06d>.png per keyframe (16-bit, millimetres; frontends with keyframe_depths(): dense)
    write_map: bool = True  # write map.npz (keyframes, points, tracks, calibration, frames) for `fgslam export`
    save_map: Optional[str] = None  # also write a stored map here (`fgslam run --save-map MAP`; fgslam/export/mapfile.py)
    extend_map: Optional[str] = None  # the stored map this recording continues (`fgslam run --map MAP`; merged when localised in it)
    map_features: MapFeaturesConfig = field(default_factory=MapFeaturesConfig)  # keyframe features of a stored map
    map_merge: MapMergeConfig = field(default_factory=MapMergeConfig)  # `--map`: when the recording is merged into the stored map
    map_join: MapJoinConfig = field(default_factory=MapJoinConfig)  # `--map`: the merged sessions optimised in one pose graph
    map_relocalize: bool = True  # `--map`, metric sensors: a lost frame is relocalised in the loaded map too while the run goes on (patch and dense families; fgslam/localize/live.py)
    rerun: RerunConfig = field(default_factory=RerunConfig)  # what `fgslam run --rerun out.rrd` logs (fgslam/export/rerun.py)


@dataclass
@with_sections(family_config_classes, after="dataset")
class SlamConfig:
    """Root configuration of ``fgslam run`` (presets: ``fgslam/configs/patch_*.yaml``).

    Besides the fields below it has one section per frontend family that has a config class, named
    after the family and placed after ``dataset`` (``patch: PatchConfig``): they come from the
    registry :data:`fgslam.frontends.FAMILIES`, so a new family needs no edit here."""

    frontend: Literal[FRONTEND_NAMES] = "patch"  # frontend family: patch, dense or pointmap
    sensor: SensorName = "mono"  # mono | stereo (needs right images) | rgbd (needs depth)
    threads: int = ranged(0, ge=0, le=MAX_THREADS)  # torch and OpenCV threads for the run (0: leave the library defaults); stages may set their own
    log_interval_frames: int = ranged(100, ge=1, le=MAX_FRAMES)  # a progress line at least every this many frames
    log_interval_s: float = ranged(10.0, gt=0, le=MAX_SCALAR)  # ... or every this many seconds, whichever comes first
    auto_align: bool = True  # evaluation alignment from the sensor (sim3 mono, se3 stereo/rgbd); false: eval.align
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    # (here: one section per frontend family, e.g. patch: PatchConfig, from the frontend registry)
    map: BackendConfig = field(default_factory=BackendConfig)  # the run's backend (fgslam/backend)
    imu: ImuServiceConfig = field(default_factory=ImuServiceConfig)  # IMU fusion (fgslam/services/imu.py; inertial presets)
    eval: EvalConfig = field(default_factory=EvalConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    # loop closure (mode off | proximity | classical | both); off by default
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    max_memory_gib: float = ranged(16.0, gt=0, le=MAX_MEMORY_MIB / 1024)  # a run whose estimated peak memory (fgslam/run/memory.py) exceeds this is refused before any work
    # user factor plugins, [{class: "package.module:ClassName", options: {...}}] (fgslam/services/plugins.py)
    factors: list[dict[str, Any]] = field(default_factory=list)

    def validate(self) -> None:
        self.loop_closure.validate()
        validate_factor_entries(self.factors)

    def family_section(self, name: str | None = None) -> Any:
        """The config section of frontend family ``name`` (default: ``frontend``); None for a family
        without one (planned families). ``Any``: the section class is the family's registry entry's
        (a user's family included)."""
        return getattr(self, name or self.frontend, None)

    def needs_colour(self) -> bool:
        """Whether the run reads the colour images: PLY colours, or a frontend whose learned source takes
        colour (the official networks' input; the built-in sources use the grey image only)."""
        family = self.family_section()
        wants = getattr(family, "wants_colour", None)
        return bool(self.output.write_ply or (wants is not None and wants()))

    def alignment(self) -> str:
        """Alignment used for the ATE: the sensor's (auto) or ``eval.align``."""
        if not self.auto_align:
            return self.eval.align
        return "sim3" if self.sensor == "mono" else "se3"


def dataset_config_for(config: SlamConfig) -> DatasetConfig:
    """``config.dataset`` with only the streams the run needs switched on (right images for stereo,
    depth for RGB-D, colour only for PLY colours or a learned source: :meth:`SlamConfig.needs_colour`); a
    stream the config switched off stays off."""
    ds = config.dataset
    return replace(
        ds,
        load_right=ds.load_right and config.sensor == "stereo",
        load_depth=ds.load_depth and config.sensor == "rgbd",
        load_rgb=ds.load_rgb and config.needs_colour(),
    )


def load_slam_config(name_or_path: str | Path | None, overrides: list[str] | tuple[str, ...] = ()) -> SlamConfig:
    """SlamConfig from a YAML path or preset name (None: defaults) with ``key=value`` overrides."""
    path = None if name_or_path is None else resolve_preset(name_or_path)
    return load_config(SlamConfig, path, overrides)
