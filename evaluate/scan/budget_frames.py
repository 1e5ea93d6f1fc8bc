"""The budget's per-frame work in chunks of frames: read, subsample, ray cast, linearise.

Why chunks: the pose refinement's cost is per frame (a render of about 2500 rays and the
pixels' linearisation at each Gauss-Newton step); only its solve couples the frames, and that is
a banded system solved in milliseconds. So the per-frame work goes out on the study's
`ChunkRunner` (this process, local processes or a Dask cluster) as small descriptors (a
recording path, frame positions and their current poses, never pixels), and every path runs
the same function on the same frames: the budget from a cluster is the one of one process.

A worker keeps what it read: the subsampled depth of the frames it has seen (about 5 kB a
frame) and one ray-casting scene of the mesh, so the later steps do not read the recording
again when their chunk lands where it ran before; elsewhere the frames are read anew (the
same pixels, the same result). All the frames of a chunk are cast in one call: per call
Open3D's overhead was most of a 2500-ray render.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from depthstation.core.camera_model import Intrinsics, pixel_rays
from depthstation.core.capture.registry import open_recording
from depthstation.core.capture.topics import TopicChoice
from depthstation.core.errors import EvaluationError
from depthstation.core.frames import FrameSource
from depthstation.core.lazy_open3d import open3d
from depthstation.core.raster import fill_rays
from depthstation.evaluate.scan import pose_refine as pr
from depthstation.evaluate.scan.chunks import _file_key
from depthstation.evaluate.scan.raycast import MeshCaster
from depthstation.evaluate.scan.reference import load_unmeasured
from depthstation.evaluate.scan.trajectory import Trajectory

F64 = NDArray[np.float64]
SAMPLE_PIXELS = 2500   # pixels per frame the refinement renders (the frame subsampled to about this)
MIN_SAMPLES = 12       # a frame with fewer usable pixels is left to the prior
CACHE_FRAMES = 200_000  # subsampled depths a worker keeps (about 5 kB each at 640x480)


def small_intrinsics(intr: Intrinsics, step: int, ox: int = 0, oy: int = 0) -> Intrinsics:
    """Every `step`-th pixel of a view from (ox, oy) as a view of its own (pixel centres coincide:
    u = ox + step u'); a lens's coefficients act on normalised coordinates and stay as they are."""
    return replace(intr, width=len(range(ox, intr.width, step)), height=len(range(oy, intr.height, step)),
                   fx=intr.fx / step, fy=intr.fy / step, ppx=(intr.ppx - ox) / step,
                   ppy=(intr.ppy - oy) / step)


def sample_step(intr: Intrinsics, pixels: int = SAMPLE_PIXELS) -> int:
    return max(1, round(math.sqrt(intr.width * intr.height / pixels)))


def pixel_offset(frame: int, step: int) -> tuple[int, int]:
    """Where frame `frame`'s subsample starts: it walks the step x step offsets frame by frame, so
    that over the frames every pixel position is sampled. Why: with one fixed subsample a thin band
    of a distance x inclination cell (a floor at grazing view) is hit in some frames and missed in
    others, and the cell's mean of a per-frame part (the pose's) is off by that aliasing."""
    k = frame % (step * step)
    return k % step, (k // step + 2 * (k % step)) % step


@dataclass(frozen=True)
class RefineChunk:
    """Frames of the refinement (their positions in the recording, and their index among the
    refinement's frames from `first` on) and where to render them: the poses of this step, or
    (first step) the trajectory to match them from by time stamp."""

    sequence: str                 # the recording's path (workers open it; its file key names the cache)
    mesh: str
    unmeasured: str | None
    intrinsics: str | None
    topics: TopicChoice | None
    positions: tuple[int, ...]
    first: int
    step: int
    z_max: float
    poses: F64 | None = None
    trajectory: Trajectory | None = None
    tolerance_s: float = 0.01
    nthreads: int = 0
    source: FrameSource | None = None  # the recording already open (in the command's process)


@dataclass
class RefineFrames:
    """A chunk's frames: time stamps, the poses they were rendered at, the samples of each."""

    stamps: F64
    poses: F64
    data: list[pr.FrameData | None]


class SampledCaster:
    """One ray-casting scene of the mesh and the rays of each subsampled view (one per offset)."""

    def __init__(self, mesh: str, unmeasured: str | None, intr: Intrinsics, step: int, nthreads: int) -> None:
        self.intr = intr
        self.step = step
        self.base = MeshCaster(mesh, small_intrinsics(intr, step), nthreads)
        if unmeasured is not None:
            self.base.mark_unmeasured(load_unmeasured(Path(unmeasured), self.base.n_triangles))
        self.dirs: dict[tuple[int, int], NDArray[np.float32]] = {}

    def view_dirs(self, offset: tuple[int, int]) -> NDArray[np.float32]:
        if offset not in self.dirs:
            self.dirs[offset] = np.ascontiguousarray(
                pixel_rays(small_intrinsics(self.intr, self.step, *offset)).reshape(-1, 3))
        return self.dirs[offset]

    def cast(self, poses: F64, offsets: list[tuple[int, int]]) -> list[tuple[F64, F64, NDArray[np.float32]]]:
        """(z-depth, world normals, ray directions) of every frame's subsampled view, in one call."""
        dirs = [self.view_dirs(o) for o in offsets]
        ends = np.cumsum([0] + [d.shape[0] for d in dirs])
        rays = np.empty((int(ends[-1]), 6), dtype=np.float32)
        for k, (pose, d) in enumerate(zip(poses, dirs, strict=True)):
            pose = np.asarray(pose, dtype=np.float64)
            fill_rays(rays[ends[k]:ends[k + 1]], pose[:3, 3].copy(), pose[:3, :3].copy(), d)
        o3d = open3d()
        ans = self.base.scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=self.base.nthreads)
        t_hit = ans["t_hit"].numpy()
        normals = ans["primitive_normals"].numpy()
        self.base._blank_unmeasured(ans["primitive_ids"].numpy(), normals)
        return [(t_hit[ends[k]:ends[k + 1]], normals[ends[k]:ends[k + 1]], dirs[k]) for k in range(len(dirs))]


@dataclass
class _Cache:
    source_key: object = None
    source: FrameSource | None = None
    caster_key: object = None
    caster: SampledCaster | None = None
    depth_key: object = None
    depths: dict[tuple[int, tuple[int, int]], tuple[float, NDArray[Any]]] | None = None


_CACHE = _Cache()


def clear_cache() -> None:
    global _CACHE
    _CACHE = _Cache()


def _source(chunk: RefineChunk) -> tuple[FrameSource, object]:
    key: object = (_file_key(chunk.sequence), chunk.intrinsics, chunk.topics)
    if chunk.source is not None:
        return chunk.source, key
    if _CACHE.source is None or _CACHE.source_key != key:
        intr = Path(chunk.intrinsics) if chunk.intrinsics else None
        _CACHE.source = open_recording(Path(chunk.sequence), intrinsics=intr, topics=chunk.topics)
        _CACHE.source_key = key
    return _CACHE.source, key


def _caster(chunk: RefineChunk, intr: Intrinsics) -> SampledCaster:
    key = (_file_key(chunk.mesh), None if chunk.unmeasured is None else _file_key(chunk.unmeasured),
           intr, chunk.step, chunk.nthreads)
    if _CACHE.caster is None or _CACHE.caster_key != key:
        _CACHE.caster = None
        _CACHE.caster = SampledCaster(chunk.mesh, chunk.unmeasured, intr, chunk.step, chunk.nthreads)
        _CACHE.caster_key = key
    return _CACHE.caster


def _depths(chunk: RefineChunk, source: FrameSource, source_key: object) -> list[tuple[float, NDArray[Any]]]:
    """(time stamp s, subsampled depth) of the chunk's frames: kept from an earlier step, or read.
    Kept by position and subsample offset (a frame's offset follows its index in the refinement)."""
    key = (source_key, chunk.step)
    if _CACHE.depths is None or _CACHE.depth_key != key or len(_CACHE.depths) > CACHE_FRAMES:
        _CACHE.depths, _CACHE.depth_key = {}, key
    kept = _CACHE.depths
    want = {(p, pixel_offset(chunk.first + k, chunk.step)) for k, p in enumerate(chunk.positions)}
    missing = sorted(w for w in want if w not in kept)
    if missing:
        first, last = missing[0][0], missing[-1][0]
        offsets = dict(missing)
        for k, fs in enumerate(source.frames(limit=last - first + 1, start=first)):
            pos = first + k
            if pos not in offsets:
                continue
            if fs.depth is None:
                raise EvaluationError(f"frame {pos} of {source.name} has no depth image on a second reading")
            ox, oy = offsets[pos]
            sub = np.ascontiguousarray(fs.depth[oy::chunk.step, ox::chunk.step])
            kept[(pos, (ox, oy))] = (fs.timestamp_ns * 1e-9, sub)
    return [kept[(p, pixel_offset(chunk.first + k, chunk.step))] for k, p in enumerate(chunk.positions)]


def refine_frames(chunk: RefineChunk) -> RefineFrames:
    """The samples of the chunk's frames rendered at their poses (the chunk's, or matched)."""
    source, source_key = _source(chunk)
    info = source.info
    intr = info.depth_intrinsics
    frames = _depths(chunk, source, source_key)
    stamps = np.array([t for t, _ in frames])
    if chunk.poses is not None:
        poses = np.asarray(chunk.poses, dtype=np.float64)
    else:
        assert chunk.trajectory is not None
        matched = [chunk.trajectory.match(t, chunk.tolerance_s) for t in stamps]
        if any(m is None for m in matched):
            raise EvaluationError(f"a frame the study used has no pose within {chunk.tolerance_s} s")
        poses = np.stack([np.asarray(m, dtype=np.float64) for m in matched if m is not None])
    caster = _caster(chunk, intr)
    offsets = [pixel_offset(chunk.first + k, chunk.step) for k in range(len(frames))]
    units = info.depth_units_m
    fb = intr.fx * (info.baseline_m or 0.05)
    data: list[pr.FrameData | None] = []
    views = caster.cast(poses, offsets)
    for (t_hit, normals, dirs), pose, (_, depth) in zip(views, poses, frames, strict=True):
        fd = pr.frame_data(t_hit, normals, dirs, pose, depth, units, fb, chunk.z_max)
        data.append(fd if fd.n >= MIN_SAMPLES else None)
    return RefineFrames(stamps, poses, data)
