"""viz: arm geometry placement, rendered pictures, rollout PNGs."""

import math

import numpy as np
import pytest
from mpl_toolkits.mplot3d.art3d import Poly3DCollection
import torch
from matplotlib.figure import Figure
from PIL import Image

from torchrl_silp import UR5e, UR5eReach, UR5eReachEnv
from torchrl_silp.viz import arm_polygons, draw_scene, render_rgb, save_rollout_png

Q = [0.3, -1.2, 1.4]
BOX = [0.4, 0.6, 0.1, 0.3, 0.0, 0.3]
GOAL = [0.5, -0.1, 0.2]


@pytest.fixture(scope="module")
def robot():
    return UR5e()


def test_arm_polygons_lie_on_the_collision_geometry(robot):
    # The sphere cover contains every primitive (tests/test_collision.py), so
    # polygons placed with the right frames and transforms lie inside it; a
    # wrong frame or a missed primitive transform puts vertices outside.
    for q in (Q, [0.0, -math.pi / 2, math.pi / 2], [-1.0, -2.5, 2.0]):
        polys, colours = arm_polygons(robot, q)
        kinds = [p.kind for p in robot.primitives]
        assert len(polys) == len(colours) == 32 * kinds.count("cylinder") + 6 * kinds.count("box")
        verts = torch.as_tensor(np.concatenate(polys), dtype=torch.float32)
        centres, radii = robot.link_spheres(torch.tensor(q))
        gap = ((verts[:, None] - centres[None]).norm(dim=-1) - radii).min(dim=1).values
        assert gap.max() < 1e-5
        # and they reach out to it: the cylinder rims touch their radius, not a shrunken mesh
        extent = verts.max(0).values - verts.min(0).values
        assert (extent > 0.1).all()


def test_render_rgb_shape_dtype_and_content(robot):
    img = render_rgb(robot, Q, BOX, GOAL, start_tcp=[0.3, 0.3, 0.3], width=200, height=150)
    assert img.shape == (150, 200, 3) and img.dtype == np.uint8
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50
    assert (img.astype(int).sum(-1) < 3 * 200).mean() > 0.05  # a good share of non-white pixels
    r, g, b = (img[..., i].astype(int) for i in range(3))
    assert ((r > g + 60) & (r > b + 60)).sum() > 50  # the red obstacle
    assert ((g > r + 40) & (g > b + 20)).sum() > 10  # the green goal


def test_render_follows_the_inputs(robot):
    base = render_rgb(robot, Q, BOX, GOAL, width=160, height=160)
    assert not np.array_equal(base, render_rgb(robot, [1.0, -1.2, 1.4], BOX, GOAL, width=160, height=160))
    moved = [0.2, 0.4, -0.2, 0.0, 0.0, 0.3]
    assert not np.array_equal(base, render_rgb(robot, Q, moved, GOAL, width=160, height=160))
    np.testing.assert_array_equal(base, render_rgb(robot, torch.tensor(Q), BOX, GOAL, width=160, height=160))


def test_draw_scene_into_given_axes(robot):
    fig = Figure()
    ax = fig.add_subplot(projection="3d")
    path = np.array([[0.3, 0.3, 0.3], [0.4, 0.1, 0.25], [0.5, -0.1, 0.2]])
    assert draw_scene(robot, Q, BOX, GOAL, start_tcp=path[0], trajectory=path, ax=ax, title="t") is ax
    assert ax.get_title() == "t"
    assert sorted(ax.get_legend_handles_labels()[1]) == ["TCP path", "goal", "start TCP"]
    with pytest.raises(TypeError, match="ax"):
        draw_scene(robot, Q, BOX, GOAL, ax=Figure().add_subplot())


def test_bad_inputs_raise(robot):
    with pytest.raises(ValueError, match="q3"):
        render_rgb(robot, [[0.0, 0.0, 0.0]], BOX, GOAL)
    with pytest.raises(ValueError, match="obstacle"):
        render_rgb(robot, Q, [0.6, 0.4, 0.1, 0.3, 0.0, 0.3], GOAL)
    with pytest.raises(ValueError, match="goal"):
        render_rgb(robot, Q, BOX, [0.0, np.nan, 0.0])
    with pytest.raises(ValueError, match="trajectory"):
        render_rgb(robot, Q, BOX, GOAL, trajectory=np.zeros((4, 2)))
    with pytest.raises(ValueError, match="width"):
        render_rgb(robot, Q, BOX, GOAL, width=0)
    with pytest.raises(TypeError, match="robot"):
        render_rgb("ur5e", Q, BOX, GOAL)


@pytest.fixture(scope="module")
def env():
    # short episodes so that a rollout holds several of them per env
    return UR5eReachEnv(num_envs=2, seed=0, max_steps=4)


def read_png(path):
    with Image.open(path) as im:
        assert im.format == "PNG"
        return np.asarray(im.convert("RGB"))


def test_save_rollout_png_batched(env, tmp_path):
    torch.manual_seed(0)
    td = env.rollout(6, break_when_any_done=False)
    assert td.batch_size == (2, 6)
    out = save_rollout_png(env, td, tmp_path / "b.png", dpi=50)
    assert out == tmp_path / "b.png"
    # 2 envs x (one 4-step episode + a 2-step tail) = 4 episodes -> 2 x 2 panels of 4 inches
    assert read_png(out).shape == (400, 400, 3)
    # a robot, or a model, or an env holding one
    for holder, name in ((env.model.robot, "c.png"), (env.model, "e.png")):
        assert read_png(save_rollout_png(holder, td, tmp_path / name, max_panels=3, dpi=50)).shape == (400, 400, 3)
    assert read_png(save_rollout_png(env, td, tmp_path / "d.png", max_panels=1, dpi=50)).shape == (200, 200, 3)


def test_save_rollout_png_unbatched(tmp_path):
    env = UR5eReachEnv(seed=1)
    assert isinstance(env.model, UR5eReach)
    torch.manual_seed(0)
    td = env.rollout(5)
    assert td.batch_size == (5,)
    img = read_png(save_rollout_png(env, td, str(tmp_path / "t.png"), dpi=50))
    assert img.shape == (200, 200, 3)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50


def test_save_rollout_png_bad_inputs(env, tmp_path):
    td = env.rollout(2)
    with pytest.raises(TypeError, match="env_or_robot"):
        save_rollout_png(object(), td, tmp_path / "x.png")
    with pytest.raises(ValueError, match="max_panels"):
        save_rollout_png(env, td, tmp_path / "x.png", max_panels=0)
    for key in ("joint_position", "obstacle", ("next", "joint_position"), ("next", "achieved_goal")):
        with pytest.raises(ValueError, match="missing"):
            save_rollout_png(env, td.exclude(key), tmp_path / "x.png")
    # the flat observation is not needed: the named keys are read
    save_rollout_png(env, td.exclude("observation", ("next", "observation")), tmp_path / "y.png", dpi=20)
    with pytest.raises(TypeError, match="rollout"):
        save_rollout_png(env, {"observation": 1}, tmp_path / "x.png")


def test_random_rollout_recipe_smoke(tmp_path, capsys):
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).parents[1] / "recipes" / "random_rollout.py"
    spec = importlib.util.spec_from_file_location("random_rollout", path)
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    out = tmp_path / "sub" / "r.png"
    metrics = recipe.main(["--num-envs", "2", "--steps", "3", "--seed", "1", "--out", str(out)])
    assert read_png(out).shape[2] == 3
    assert metrics["episodes"] >= 2
    assert 0.0 <= metrics["collision_rate"] <= 1.0 and 0.0 <= metrics["success_rate"] <= 1.0
    assert metrics["mean_reward"] <= 1.0
    printed = capsys.readouterr().out
    assert "collision rate" in printed and str(out) in printed
    with pytest.raises(SystemExit):
        recipe.main(["--steps", "0"])


def test_the_panda_is_drawn_from_its_own_primitives_with_every_box(tmp_path):
    from torchrl_silp import Panda, PandaReach, ReachEnv
    from torchrl_silp.viz import arm_polygons, draw_scene, save_rollout_png

    panda = Panda()
    q = 0.5 * (panda.joint_low + panda.joint_high)
    polys, colours = arm_polygons(panda, q)
    kinds = [p.kind for p in panda.primitives]
    # every primitive is drawn: a cylinder 16 sides + 2 x 8 cap quads, a box 6 faces, a sphere its mesh
    assert len(polys) == len(colours) >= 32 * kinds.count("cylinder") + 6 * kinds.count("box")
    _, pos = panda.frames(q)
    frames = pos.numpy()
    drawn = np.concatenate(polys)
    # the solids sit on the arm: every vertex within a link's radius (< 0.15 m) of the frames' chain
    reach = np.linalg.norm(frames - frames[0], axis=-1).max()
    assert np.isfinite(drawn).all() and np.linalg.norm(drawn - frames[0], axis=-1).max() <= reach + 0.15
    two_boxes = [0.3, 0.4, -0.1, 0.0, 0.0, 0.2, 0.5, 0.6, 0.1, 0.2, 0.0, 0.3]
    ax = draw_scene(panda, q, two_boxes, [0.5, 0.0, 0.3])
    ax.figure.canvas.draw()
    (solids,) = [c for c in ax.collections if isinstance(c, Poly3DCollection) and c.get_zorder() == 2]
    assert len(solids.get_paths()) == len(polys) + 2 * 6  # the arm's faces and both boxes' six
    with pytest.raises(ValueError, match="6 numbers each"):
        draw_scene(panda, q, two_boxes[:7], [0.5, 0.0, 0.3])
    env = ReachEnv(PandaReach(num_boxes=2), num_envs=2, seed=0)
    torch.manual_seed(0)
    out = save_rollout_png(env, env.rollout(4), tmp_path / "panda.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
