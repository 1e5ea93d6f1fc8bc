"""Where a command's rerun recording goes: an `.rrd` file, a spawned viewer, or a local web viewer."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class RerunTarget:
    """The `--rrd FILE`, `--spawn` and `--serve` options of a command."""

    rrd: Path | None = None
    spawn: bool = False
    serve: bool = False

    @property
    def enabled(self) -> bool:
        return self.rrd is not None or self.spawn or self.serve


@contextmanager
def recording(app_id: str, target: RerunTarget, blueprint: Any = None,
              description: str | None = None) -> Iterator[Any]:
    """Yield a rerun RecordingStream (or None when no target is set); flushed and closed on exit.

    rerun is imported only when a target is set, so commands without `--rrd` never pay for it.
    The web viewer binds to localhost only.
    """
    if not target.enabled:
        yield None
        return
    import rerun as rr

    rec = rr.RecordingStream(app_id)
    if target.rrd is not None:
        Path(target.rrd).parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(target.rrd), default_blueprint=blueprint)
    if target.spawn:
        rec.spawn(default_blueprint=blueprint)
    if target.serve:
        uri = rec.serve_grpc(default_blueprint=blueprint)
        rr.serve_web_viewer(connect_to=uri, open_browser=False)
    if description:
        rec.log("description", rr.TextDocument(description, media_type=rr.MediaType.MARKDOWN), static=True)
    try:
        yield rec
    finally:
        rec.flush()
        rec.disconnect()
