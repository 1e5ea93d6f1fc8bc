"""A sensor model: a camera preset plus an ordered list of effects, read from and written to TOML."""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from depthstation.core.errors import InputError, SimulationError
from depthstation.core.text_files import read_text
from depthstation.core.tomlcompat import tomllib
from depthstation.simulate.effects import EFFECTS
from depthstation.simulate.effects.base import Array, Effect, PixelContext
from depthstation.simulate.effects.generic import never_positive, term_class, term_spec
from depthstation.simulate.fastpath import FusedSampler, fusable
from depthstation.simulate.presets import PRESETS, CameraPreset

MODEL_DIR = Path(__file__).resolve().parent / "models"


@dataclass
class SensorModel:
    """What the simulator renders with and what `explain` fits: camera geometry and effects.

    `effects` are kept in physical order (their `stage`: disparity biases, disparity noise, depth
    scale, quantisation, depth artefacts, reference errors, dropout), stable within a stage.
    """

    name: str
    camera: CameraPreset
    effects: list[Effect] = field(default_factory=list)
    camera_overrides: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.effects = sorted(self.effects, key=lambda e: e.stage)
        self._lock = threading.Lock()
        self._fused: tuple[Any, ...] | None = None  # (key, sampler, ctx, z) of the last context

    def effect(self, name: str) -> Effect | None:
        """The effect of that catalogue name, or None when the model lacks it."""
        return next((e for e in self.effects if e.name == name), None)

    def bias_m(self, ctx: PixelContext) -> Array:
        """Sum of the effects' analytic z biases (first order: effects assumed small and independent)."""
        out = np.zeros(ctx.shape())
        for e in self.effects:
            out = out + e.bias_m(ctx)
        return out

    def variance_m2(self, ctx: PixelContext) -> Array:
        """Sum of the effects' analytic z variances."""
        out = np.zeros(ctx.shape())
        for e in self.effects:
            out = out + e.variance_m2(ctx)
        return out

    def valid_probability(self, ctx: PixelContext) -> Array:
        """Probability that a pixel has depth (product over the effects)."""
        out = np.ones(ctx.shape())
        for e in self.effects:
            out = out * e.valid_probability(ctx)
        return out

    def sample(self, ctx: PixelContext, z_m: Array, rng: np.random.Generator, *,
               fused: bool = True) -> Array:
        """One measured z map (float32, NaN = no depth) from a true one; z_m is not modified.

        Models made only of disparity shifts/noise, scale, quantisation, flying pixels and dropout
        (the default ones) run through one fused pass (`simulate.fastpath`), the same model in
        distribution; others apply effect by effect (`fused=False` forces that).
        """
        if fused and ctx is not None and fusable(self.effects):
            # the last context's sampler is kept (a standpoint samples one context 150 times);
            # it is built outside the lock, so renderers on several threads build theirs side by side
            key = (id(ctx), id(z_m))
            with self._lock:
                last = self._fused
            if last is not None and last[0] == key:
                sampler = last[1]
            else:
                sampler = FusedSampler(self.effects, ctx, z_m)
                with self._lock:
                    self._fused = (key, sampler, ctx, z_m)
            return sampler.sample(rng)
        z = np.array(z_m, dtype=np.float32, copy=True)
        for e in self.effects:
            z = e.apply(ctx, z, rng)
        return z

    def to_dict(self) -> dict[str, Any]:
        return {"camera": {"preset": self.camera.name, **self.camera_overrides},
                "effects": {e.name: dict(e.params) for e in self.effects}}

    def to_toml(self) -> str:
        """The model as TOML that `load_model` reads back to the same model."""
        lines = [f"# sensor model '{self.name}' (depthstation simulate)", "[camera]",
                 f'preset = "{self.camera.name}"']
        lines += [f"{k} = {_toml_value(v)}" for k, v in self.camera_overrides.items()]
        for e in self.effects:
            lines += ["", f"# {e.meaning}"] if e.meaning else [""]
            if e.source:
                lines += [f"# source: {e.source}"]
            lines += [f"[effects.{e.name}]"]
            lines += [f"{k} = {_toml_value(v)}  # {e.units[k]}" for k, v in e.params.items()]
        return "\n".join(lines) + "\n"

    def with_effect(self, name: str, **params: float) -> SensorModel:
        """A copy with one effect added or its parameters replaced (what `explain` proposes)."""
        effects = [e for e in self.effects if e.name != name]
        old = self.effect(name)
        merged = {**(old.params if old else {}), **params}
        effects.append(make_effect(name, merged))
        return SensorModel(self.name, self.camera, effects, dict(self.camera_overrides))

    def white_noise(self) -> SensorModel:
        """A copy whose window-shared noise is white: `window_noise` folded into `disparity_noise` at
        the same total variance. For checks that treat pixels as independent samples (a mean's
        standard error from the pixel count), which the window's sharing would break."""
        window = self.effect("window_noise")
        if window is None:
            return self
        white = self.effect("disparity_noise")
        total = float(np.hypot(white.params["sigma_px"] if white else 0.0, window.params["sigma_px"]))
        return self.without_effect("window_noise").with_effect("disparity_noise", sigma_px=total)

    def without_effect(self, name: str) -> SensorModel:
        return SensorModel(self.name, self.camera, [e for e in self.effects if e.name != name],
                           dict(self.camera_overrides))


def _toml_value(v: Any) -> str:
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(float(v))


def make_effect(name: str, params: dict[str, Any] | None = None) -> Effect:
    """Instantiate a catalogue effect or a generic term (`term_...`, simulate.effects.generic) by name."""
    cls = EFFECTS.get(name) or term_class(name)
    if cls is None:
        raise SimulationError(f"unknown effect '{name}' (catalogue: {', '.join(EFFECTS)}; "
                              "or a generic term_<bias|noise>_<axes>_<basis>)")
    try:
        return cls(params or {})
    except ValueError as exc:
        raise SimulationError(f"effect '{name}': {exc}") from exc


def model_from_dict(data: dict[str, Any], name: str, source: Path | None = None) -> SensorModel:
    """Validate a parsed model TOML; errors name the key."""
    for k in data:
        if k not in ("camera", "effects"):
            raise InputError(source, f"model: unknown key '{k}' (expected [camera] and [effects.*])")
    if not isinstance(data.get("camera"), dict) or "preset" not in data["camera"]:
        raise InputError(source, "model: missing key 'camera.preset' (d455, d435 or d415: the camera "
                                 "whose geometry the model starts from)")
    cam = dict(data["camera"])
    preset_name = str(cam.pop("preset")).lower()
    if preset_name not in PRESETS:
        known = ', '.join(PRESETS)
        raise InputError(source, f"model: camera.preset '{preset_name}' unknown (known: {known})")
    try:
        camera = PRESETS[preset_name].with_overrides(cam).check()
    except KeyError as exc:
        raise InputError(source, f"model: unknown key 'camera.{exc.args[0]}'") from exc
    except (TypeError, ValueError) as exc:
        raise InputError(source, f"model: [camera] {exc}") from exc
    effects_data = data.get("effects", {})
    if not isinstance(effects_data, dict):
        raise InputError(source, "model: [effects] must be a table of tables")
    effects: list[Effect] = []
    for ename, params in effects_data.items():
        if not isinstance(params, dict):
            raise InputError(source, f"model: [effects.{ename}] must be a table")
        try:
            cls = EFFECTS.get(ename) or term_class(ename)
        except SimulationError as exc:   # a term name whose basis and axes do not go together
            raise InputError(source, f"model: {exc}") from exc
        spec = cls.PARAMS if cls is not None else {}   # generic terms too: every parameter required
        unknown = [k for k in params if k not in spec]
        if spec and unknown:  # a misspelt name first: else it would read as the right one missing
            raise InputError(source, f"model: unknown parameter 'effects.{ename}.{unknown[0]}' "
                                     f"(known: {', '.join(spec)})")
        optional = cls.OPTIONAL if cls is not None else frozenset()
        missing = [k for k in spec if k not in params and k not in optional]
        if missing:  # an effect named without its value would run at a default nobody chose
            _, unit, meaning = spec[missing[0]]
            raise InputError(source, f"model: missing key 'effects.{ename}.{missing[0]}' ({unit}: {meaning})")
        bad = [k for k, v in params.items() if isinstance(v, (int, float)) and not math.isfinite(float(v))]
        if bad:
            raise InputError(source, f"model: 'effects.{ename}.{bad[0]}' must be finite")
        try:
            effects.append(make_effect(ename, params))
        except SimulationError as exc:
            raise InputError(source, f"model: {exc}") from exc
        _check_effect(effects[-1], camera, source)
    return SensorModel(name, camera, effects, cam)


def _check_effect(effect: Effect, camera: CameraPreset, source: Path | None) -> None:
    """What a single effect's own check cannot see: a noise term that is a negative variance
    wherever it is evaluated (clipped to nothing without a word), and a quantisation unit the
    camera's depth units override."""
    spec = term_spec(effect)
    if spec is not None and spec.quantity == "noise" and never_positive(spec, effect.params):
        coefs = ", ".join(f"{c} = {effect.params[c]:g}" for c in spec.coefficients)
        raise InputError(source, f"model: [effects.{effect.name}] is a variance ({spec.unit}) below zero "
                                 f"everywhere ({coefs}): a noise term adds variance, its value must be >= 0")
    if effect.name == "quantization":
        unit = effect.params["depth_unit_m"]
        if abs(unit - camera.depth_units_m) > 1e-9 * camera.depth_units_m:
            raise InputError(source, f"model: 'effects.quantization.depth_unit_m' = {unit:g} m differs from "
                                     f"the camera's depth units {camera.depth_units_m:g} m ([camera] "
                                     "depth_units_m, the preset's unless set): depth is written in the "
                                     "camera's units, so give both the same value")


def check_seed(seed: int) -> None:
    """The noise generators take seeds of 0 and up (numpy refuses a negative one mid-run)."""
    if seed < 0:
        raise InputError(None, f"--seed must be 0 or more, not {seed}")


def load_model(name_or_path: str | Path | SensorModel = "d455") -> SensorModel:
    """A model from a preset name ('d455', 'd435', 'd415' -> simulate/models/<name>.toml) or a TOML path."""
    if isinstance(name_or_path, SensorModel):
        return name_or_path
    p = Path(name_or_path)
    if not p.exists() and not p.suffix and (MODEL_DIR / f"{str(name_or_path).lower()}.toml").is_file():
        p = MODEL_DIR / f"{str(name_or_path).lower()}.toml"
    if not p.is_file():
        raise InputError(p, f"model not found (a preset {', '.join(PRESETS)} or a model TOML)")
    try:
        data = tomllib.loads(read_text(p, "model TOML"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(p, f"not valid TOML ({exc})") from exc
    return model_from_dict(data, p.stem, p)


def model_from_toml(text: str, name: str = "model") -> SensorModel:
    """A model from TOML text (e.g. the copy kept in a truth.json)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(None, f"model: not valid TOML ({exc})") from exc
    return model_from_dict(data, name)
