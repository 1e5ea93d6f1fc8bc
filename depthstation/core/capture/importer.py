"""Import RealSense recordings, PNG folders and MCAPs into a new capture session."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from depthstation.core.capture.mcap_reader import cut_source
from depthstation.core.capture.recording import Recording
from depthstation.core.capture.registry import check_distinct_recordings, open_inputs
from depthstation.core.capture.session import Session
from depthstation.core.capture.topics import TopicChoice

# Frame sets in flight between the reader and the writer thread. A camera needs a deep queue (it
# must never wait); an import waits anyway, and a short queue lets the memory of finished frames be
# reused: with 64 in flight every 1280x720 image of a sqlite3 bag arrived in fresh pages, and
# zeroing them held the import to ~125 frame sets/s (~350 with 4; benchmarks/bench_ros_import.py).
IMPORT_QUEUE_FRAMES = 4


def import_recordings(
    sources: Sequence[Path],
    out: Path,
    *,
    compression: str = "none",
    on_frame: Callable[[Recording, int], None] | None = None,
    topics: TopicChoice | None = None,
) -> Session:
    """Convert every standpoint of `sources` into one MCAP each in the new session `out`.

    Standpoints keep their names (file or folder stem); clashes get a `-2`, `-3` suffix.
    """
    recordings = open_inputs(list(sources), topics)
    check_distinct_recordings(recordings)
    device: dict[str, Any] = dict(recordings[0].metadata.get("device") or recordings[0].info.device)
    session = Session.create(Path(out), device=device, imported_from=[str(r.path) for r in recordings])
    used: set[str] = set()
    for rec in recordings:
        name = rec.name
        k = 2
        while name in used:
            name, k = f"{rec.name}-{k}", k + 1
        used.add(name)
        meta = {
            key: value
            for key, value in rec.metadata.items()
            if key not in ("protocol", "calibration", "standpoint", "format")
        }
        meta["source"] = dict(rec.metadata.get("source") or {}, path=str(rec.path))
        standpoint = dict(rec.metadata.get("standpoint") or {})
        standpoint.pop("name", None)
        standpoint.setdefault("source", str(rec.path))
        with session.standpoint_writer(
            name, rec.info, standpoint, compression=compression, metadata=meta, blocking=True,
            queue_frames=IMPORT_QUEUE_FRAMES,
        ) as w:
            for temps_name, (times, values) in rec.temperatures().items():
                for t, v in zip(times, values, strict=True):
                    w.write_temperature(t, {temps_name: v})
            for i, fs in enumerate(rec.frames()):
                w.write(fs)
                if on_frame is not None:
                    on_frame(rec, i)
            cut = cut_source(rec)  # cut itself, or an earlier cut kept: every later study warns
            if cut is not None:
                w.entry["source_truncated"] = cut
                w.set_metadata("source", dict(meta["source"], truncated=True, cut_path=cut["path"],
                                              recovered_frames=cut["recovered_frames"]))
    return session
