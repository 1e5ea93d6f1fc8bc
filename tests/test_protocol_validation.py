"""Protocol values that cannot make a plan are refused at load, one line naming the file and key."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_acquire_session import TINY_TOML

from depthstation.core.errors import ProtocolError
from depthstation.core.protocol import MAX_STANDPOINTS, check_for_acquisition, load_protocol


@pytest.mark.parametrize(("old", "new", "says"), [
    ("max_distance_m = 1.8", "max_distance_m = inf", "'plan.max_distance_m' must be a finite number"),
    ("max_distance_m = 1.8", "max_distance_m = 1e7", f"at most {MAX_STANDPOINTS}"),
    ("step_m = 0.8", "step_m = 1e-9", "check plan.step_m"),
    ("step_m = 0.8", "step_m = nan", "'plan.step_m' must be a finite number"),
    ("fps = 30", "fps = 30\ndepth = false", "'streams.depth' must be true"),
    ("fps = 30", 'fps = 30\npreset = "HighAccuracyy"', "'streams.preset' 'HighAccuracyy' is no RealSense"),
    ("width = 640", "width = 100000", "beyond any RealSense stream"),
    ("on_chip = true", "on_chip = true\ntare = true", "'calibration.tare_distance_m' is missing"),
    ("inclinations_deg = [0.0]", "inclinations_deg = [0.0, 15.0, 15.0, 45.0]",
     "'plan.inclinations_deg' lists 15 deg more than once"),
    ("[plan]", '[device]\nmodel = "D45"\n\n[plan]', "'device.model' 'D45' is no RealSense model name"),
    ("window_minutes = 0.5", "window_minutes = 100.0", "'warmup.window_minutes' (100.0) is longer than"),
])
def test_bad_plan_values_are_refused_at_load(tmp_path: Path, old: str, new: str, says: str) -> None:
    p = tmp_path / "bad.toml"
    assert old in TINY_TOML
    p.write_text(TINY_TOML.replace(old, new))
    with pytest.raises(ProtocolError) as exc:
        load_protocol(p)
    assert str(exc.value).startswith(f"{p}: ") and says in str(exc.value)


def test_known_presets_and_the_shipped_protocols_load(tmp_path: Path) -> None:
    p = tmp_path / "ok.toml"
    p.write_text(TINY_TOML.replace("fps = 30", 'fps = 30\npreset = "high_accuracy"'))
    assert load_protocol(p).streams.preset == "high_accuracy"
    for name in ("checkerboard-d455", "demo-d455"):
        assert load_protocol(name).plan.standpoints()


def test_acquire_needs_colour(tmp_path: Path) -> None:
    """Guidance finds the board in colour: acquire refuses a protocol without it (simulate may use one)."""
    p = tmp_path / "depth_only.toml"
    p.write_text(TINY_TOML.replace("fps = 30", "fps = 30\ncolor = false"))
    proto = load_protocol(p)
    with pytest.raises(ProtocolError, match=r"depth_only.toml: 'streams.color' must be true for acquire"):
        check_for_acquisition(proto)


def test_empty_protocol_name_is_said_plainly() -> None:
    with pytest.raises(ProtocolError, match="--protocol is empty"):
        load_protocol("")


@pytest.mark.parametrize(("model", "name", "fits"), [
    ("D455", "Intel RealSense D455", True),
    ("D455", "RealSense D455", True),
    ("d455", "Intel RealSense D455", True),
    ("D435", "Intel RealSense D435I", False),   # not a substring match
    ("D455", "Intel RealSense D456", False),
    ("D455", "RealSense D455 (USB 2)", True),   # no model at the end: the model as a word
    ("D455", "RealSense D4550 prototype", False),
])
def test_a_recording_of_another_model_does_not_fit_the_protocol(tmp_path: Path, model: str, name: str,
                                                                fits: bool) -> None:
    from depthstation.acquire.station import recording_misfits
    from depthstation.simulate.simulated_camera import SimulatedCamera

    p = tmp_path / "p.toml"
    p.write_text(TINY_TOML.replace("[plan]", f'[device]\nmodel = "{model}"\n\n[plan]'))
    proto = load_protocol(p)
    info = SimulatedCamera("d455-ideal").start(proto.streams)
    info = replace(info, device={**(info.device or {}), "name": name})
    said = recording_misfits(info, proto)
    assert (said == []) is fits, said
    if not fits:
        assert said == [f"recorded by {name}, the protocol is for a {model}"]


def test_a_recording_at_another_frame_rate_does_not_fit_the_protocol(tmp_path: Path) -> None:
    """A 30 fps recording played for a 15 fps protocol: session.json said 15 fps, no word."""
    from depthstation.acquire.station import recording_misfits
    from depthstation.simulate.simulated_camera import SimulatedCamera

    p = tmp_path / "p.toml"
    p.write_text(TINY_TOML.replace("fps = 30", "fps = 15"))
    proto = load_protocol(p)
    info = SimulatedCamera("d455-ideal").start(replace(proto.streams, fps=30))
    assert recording_misfits(info, proto) == ["30 fps, the protocol asks 15"]
    assert recording_misfits(replace(info, fps=15.0), proto) == []
