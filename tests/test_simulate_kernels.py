"""The simulator's compiled per-pixel passes against their definitions, written here in numpy.

The walk of `simulate scan` renders every frame from a new pose, so the per-pose maps run through
compiled kernels, tables and in-place numpy; each must give the floats of the formula it replaces.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from depthstation.simulate.effects.base import Effect, PixelContext
from depthstation.simulate.effects.dropout import Dropout
from depthstation.simulate.effects.flying_pixels import FlyingPixels
from depthstation.simulate.model import load_model
from depthstation.simulate.scan_sequence import scan_trajectory
from depthstation.simulate.scene import load_scene
from depthstation.simulate.scene_render import SceneRaster, encode_srgb, render_geometry
from depthstation.simulate.view_renderer import depth_to_z16


def _srgb(x: np.ndarray) -> np.ndarray:
    return np.clip(255.0 * np.power(np.clip(x, 0, 1), 1 / 2.2) + 0.5, 0, 255).astype(np.uint8)


def test_srgb_table_is_the_formula() -> None:
    # every 97th float32 in [2^-31, 1], the values around each output step, and odd ones
    bits = np.arange(0x30000000, 0x3F800001, 97, dtype=np.uint32)
    x = bits.view(np.float32)
    steps = ((np.arange(256) - 0.5) / 255.0) ** 2.2
    s32 = steps.astype(np.float32)
    near = np.concatenate([s32, np.nextafter(s32, np.float32(0)), np.nextafter(s32, np.float32(2))])
    odd = np.array([0.0, -0.0, -1.0, 1.0, 1.5, np.inf, 1e-30, 1e-45], np.float32)
    for chunk in (x, near, odd):
        assert np.array_equal(encode_srgb(chunk), _srgb(chunk))
    img = np.random.default_rng(3).uniform(-0.2, 1.2, (48, 64, 3)).astype(np.float32)
    out = encode_srgb(img)
    assert out.shape == img.shape and np.array_equal(out, _srgb(img))


def test_z16_is_rint_of_the_scaled_depth() -> None:
    rng = np.random.default_rng(0)
    for dt in (np.float32, np.float64):
        z = rng.uniform(-1, 70, (60, 80)).astype(dt)
        z[0, :7] = [np.nan, np.inf, -np.inf, 0.0005, 0.0015, 0.0025, 65.535]
        for unit in (0.001, 0.0001):
            counts = np.rint(np.nan_to_num(z, nan=0.0, posinf=0.0, neginf=0.0) * np.float32(1.0 / unit))
            want = np.where((counts < 0) | (counts > 65535), 0, counts).astype(np.uint16)
            assert np.array_equal(depth_to_z16(z, unit), want)


def _keep(ctx: PixelContext, p: dict[str, float]) -> np.ndarray:
    """The dropout's keep probability as its docstring states it."""
    def logistic(x: np.ndarray) -> np.ndarray:
        return np.asarray(1.0 / (1.0 + np.exp(-np.clip(x, -60, 60))))
    z = np.asarray(ctx.z_m, dtype=np.float64)
    keep = (ctx.focal_baseline / z <= p["max_disparity_px"]).astype(np.float64)
    keep = keep * (1 - logistic((z - p["range_z50_m"]) / p["range_width_m"]))
    keep = keep * (1 - logistic((np.asarray(ctx.inclination_deg, np.float64) - p["grazing_deg50"])
                                / p["grazing_width_deg"]))
    keep = keep * (1 - p["dark_probability"] * (1 - np.clip(np.asarray(ctx.albedo, np.float64), 0, 1)))
    keep = keep * (1 - p["base_probability"])
    return np.broadcast_to(keep, ctx.shape())


def test_dropout_keep_probability_is_its_formula() -> None:
    rng = np.random.default_rng(1)
    z = rng.uniform(0.3, 9, (30, 40)).astype(np.float32)
    z[0, :5] = np.nan
    inc = rng.uniform(0, 90, (30, 40)).astype(np.float32)
    inc[1, :3] = np.nan
    alb = rng.uniform(-0.1, 1.2, (30, 40)).astype(np.float32)
    for d in (Dropout(), Dropout(base_probability=0.1, dark_probability=0.5)):
        for ctx in (PixelContext(z_m=z, inclination_deg=inc, albedo=alb),
                    PixelContext(z_m=2.0, inclination_deg=inc), PixelContext(z_m=z, inclination_deg=30.0),
                    PixelContext(z_m=3.0)):
            got, want = d.valid_probability(ctx), _keep(ctx, d.params)
            assert got.shape == want.shape and np.array_equal(got, want, equal_nan=True)


def test_flying_pixel_table_holds_every_pixel_above_its_threshold() -> None:
    e = np.random.default_rng(2).uniform(0.5, 30, (40, 50)).astype(np.float32)
    e[0, :3] = [np.inf, np.nan, 0.5]
    for params in ({}, {"width_px": 3.0, "edge_probability": 0.9}, {"edge_probability": 1e-5}):
        f = FlyingPixels(params)
        ctx = PixelContext(z_m=np.ones(e.shape, np.float32), edge_distance_px=e)
        p = (f.params["edge_probability"] * np.exp(-np.maximum(e.astype(np.float64) - 0.5, 0.0)
                                                   / f.params["width_px"])).ravel()
        idx, prob = f.near_table(ctx, e.shape)
        assert np.array_equal(idx, np.flatnonzero(p > 1e-4)) and np.array_equal(prob, p[p > 1e-4])


def test_effect_memo_answers_each_context_with_its_own_value() -> None:
    # renderers on two threads share the model's effects, each with its own context
    eff = Effect()
    errors: list[str] = []

    def run(k: int) -> None:
        for _ in range(80):  # a new context per frame, as in a walk
            ctx = PixelContext(z_m=float(k))

            def make() -> float:
                time.sleep(0.0003 * (1 + 3 * k))  # the other thread switches the memo meanwhile
                return float(k)
            for _ in range(2):  # made, then remembered
                if eff.cached(ctx, "value", make) != float(k):
                    errors.append(f"context {k} got another context's value")
                time.sleep(0.0005)

    threads = [threading.Thread(target=run, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors[:3]


@pytest.mark.parametrize("frame", [0, 300])
def test_rasterised_geometry_equals_ray_casting(frame: int) -> None:
    # the walk's views of the room: every map from the rasteriser's hit triangles equals the map
    # from Open3D's rays and per-pixel normals
    model = load_model("d455-ideal")
    scene = load_scene("room")
    _, poses = scan_trajectory("walk", scene, 30.0, frame + 1)
    intr = model.camera.stream_info(320, 240, 30.0).depth_intrinsics
    a = render_geometry(scene, intr, poses[frame], SceneRaster(scene))
    b = render_geometry(scene, intr, poses[frame], scene.raycasting_scene())
    assert np.isfinite(a.z_m).mean() > 0.5
    for k in ("z_m", "normal", "inclination_deg", "cos_inc", "albedo", "surface", "points_world",
              "edge_distance_px"):
        assert np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True), k



@pytest.mark.parametrize("standpoint", [0, 7, 13])
def test_board_views_rasterised_equal_ray_casting(standpoint: int) -> None:
    # the renderers' default for boards: every geometry map and the colour image (the print's
    # exact coverage included) as with Open3D's ray casting
    from depthstation.core.protocol import load_protocol
    from depthstation.simulate.checkerboard_session import stream_info_for
    from depthstation.simulate.poses import standpoint_pose
    from depthstation.simulate.scene import board_scene
    from depthstation.simulate.scene_render import render_color_linear

    proto = load_protocol("checkerboard-d455")
    info = stream_info_for(proto, load_model("d455-ideal"))
    intr, ci = info.depth_intrinsics.scaled(640, 360), info.color_intrinsics
    assert ci is not None
    ci = ci.scaled(640, 360)
    scene = board_scene(proto.board)
    sp = proto.plan.standpoints()[standpoint]
    pose = standpoint_pose(proto.board, sp.distance_m, sp.inclination_deg, sp.side)
    raster, cast = SceneRaster(scene), scene.raycasting_scene()
    a, b = render_geometry(scene, intr, pose, raster), render_geometry(scene, intr, pose, cast)
    assert np.isin(a.surface, [i for i, s in enumerate(scene.surfaces) if s.board_face]).mean() > 0.01
    for k in ("z_m", "normal", "inclination_deg", "cos_inc", "albedo", "surface", "points_world",
              "edge_distance_px"):
        assert np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True), k
    cpose = pose @ np.linalg.inv(info.depth_to_color.matrix)
    assert np.array_equal(render_color_linear(scene, ci, cpose, raster),
                          render_color_linear(scene, ci, cpose, cast))


def test_distorted_views_fall_back_to_ray_casting() -> None:
    # no pinhole grid to rasterise: the default renderer casts the rays with Open3D's scene
    from dataclasses import replace

    model = load_model("d455-ideal")
    scene = load_scene("room")
    intr = replace(model.camera.stream_info(320, 240, 30.0).depth_intrinsics, model="brown_conrady",
                   coeffs=(0.05, -0.01, 0.0, 0.0, 0.0))
    assert intr.has_distortion
    _, poses = scan_trajectory("walk", scene, 30.0, 1)
    a = render_geometry(scene, intr, poses[0])
    b = render_geometry(scene, intr, poses[0], scene.raycasting_scene())
    assert np.isfinite(a.z_m).mean() > 0.5
    for k in ("z_m", "normal", "surface", "points_world", "cos_inc"):
        assert np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True), k
