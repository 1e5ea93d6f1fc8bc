"""A capture survives a kill at every step of a standpoint's life: open, recording, closing, rename,
session save. Each case kills a recording process (os._exit, as SIGKILL would) at that step; the
session opened afterwards says the truth about every file and a resume can go on: a standpoint cut
before its file was finished is re-recordable, one that was finished is adopted, never lost."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from depthstation.core.capture.registry import open_inputs
from depthstation.core.capture.sample_recordings import sample_frames, sample_info
from depthstation.core.capture.session import Session
from depthstation.core.errors import InputError

FRAMES = 6

# what each kill point patches in the recording process (the patch calls os._exit(9))
KILLERS = {
    "open": """
        orig = mw.McapFileWriter.__init__
        def patched(self, *a, **k):
            os._exit(9)
        mw.McapFileWriter.__init__ = patched
    """,
    "recording": """
        orig = mw.McapFileWriter.write
        count = [0]
        def patched(self, fs):
            count[0] += 1
            if count[0] > 3:
                os._exit(9)
            return orig(self, fs)
        mw.McapFileWriter.write = patched
    """,
    "closing": """
        orig = mw.McapFileWriter.close
        def patched(self):
            os._exit(9)
        mw.McapFileWriter.close = patched
    """,
    "rename": """
        orig = pathlib.Path.replace
        def patched(self, target):
            out = orig(self, target)
            if str(target).endswith("standpoint_02.mcap"):
                os._exit(9)
            return out
        pathlib.Path.replace = patched
    """,
    "session save": """
        orig = session_mod._atomic_json
        def patched(path, data):
            entries = data.get("standpoints", [])
            if any(e["name"] == "standpoint_02" and e.get("status") == "complete" for e in entries):
                tmp = path.with_name(path.name + ".tmp")
                tmp.write_text("{ torn")
                os._exit(9)
            return orig(path, data)
        session_mod._atomic_json = patched
    """,
}


def record_then_die(sdir: Path, point: str) -> subprocess.CompletedProcess[str]:
    script = "\n".join([
        "import os, sys, pathlib",
        "from depthstation.core.capture import mcap_writer as mw",
        "from depthstation.core.capture import session as session_mod",
        "from depthstation.core.capture.sample_recordings import sample_frames, sample_info",
        textwrap.dedent(KILLERS[point]),
        "info = sample_info(32, 24)",
        "s = session_mod.Session.open(pathlib.Path(sys.argv[1]))",
        "with s.standpoint_writer('standpoint_02', info, {'distance_m': 1.5}, blocking=True) as w:",
        f"    for f in sample_frames(info, {FRAMES}, seed=4):",
        "        w.write(f)",
        "print('survived')",
    ])
    return subprocess.run([sys.executable, "-c", script, str(sdir)], capture_output=True, text=True,
                          timeout=60)


def first_standpoint(sdir: Path) -> None:
    info = sample_info(32, 24)
    s = Session.create(sdir, device={"name": "test"})
    with s.standpoint_writer("standpoint_01", info, {"distance_m": 1.0}, blocking=True) as w:
        for f in sample_frames(info, FRAMES, seed=3):
            w.write(f)


@pytest.mark.parametrize("point", list(KILLERS))
def test_every_kill_point_keeps_the_capture(tmp_path: Path, point: str) -> None:
    sdir = tmp_path / "s"
    first_standpoint(sdir)
    proc = record_then_die(sdir, point)
    assert proc.returncode == 9, proc.stdout + proc.stderr
    s = Session.open(sdir)  # what `--resume` and `capture info` see
    by_name = {e["name"]: e for e in s.standpoints}
    assert by_name["standpoint_01"]["status"] == "complete"
    second = by_name.get("standpoint_02")
    finished = point in ("rename", "session save")
    if finished:  # the file was whole: adopted, not lost, and not re-recorded
        assert second is not None and second["status"] == "complete", s.standpoints
        assert second["frames"] == FRAMES and second["file"] == "standpoint_02.mcap"
        with pytest.raises(InputError, match="never overwritten"):
            s.standpoint_writer("standpoint_02", sample_info(32, 24), {})
        names = [r.name for r in open_inputs([sdir])]
        assert names == ["standpoint_01", "standpoint_02"]
        assert [r.frame_count for r in s.recordings()] == [FRAMES, FRAMES]
    else:  # cut before its file was finished: marked partial, recorded again on resume
        assert second is None or second["status"] == "partial", s.standpoints
        info = sample_info(32, 24)
        with s.standpoint_writer("standpoint_02", info, {}, blocking=True) as w:
            for f in sample_frames(info, FRAMES, seed=5):
                w.write(f)
        assert Session.open(sdir).status("standpoint_02") == "complete"
    on_disk = json.loads((sdir / "session.json").read_text())  # saved whole, never torn
    assert on_disk["standpoints"][0]["name"] == "standpoint_01"
