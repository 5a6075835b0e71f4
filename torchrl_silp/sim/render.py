"""Pictures of the twin: MuJoCo's offscreen renderer (EGL on a headless machine) and frame strips."""

from __future__ import annotations

import numpy as np

__all__ = ["FrameRecorder", "save_strip"]


class FrameRecorder:
    """An ``on_step`` callback of :func:`~torchrl_silp.sim.run_transfer` / ``run_pick_place`` that renders one
    world of the twin after each control step (MuJoCo's offscreen renderer; on a headless machine set
    ``MUJOCO_GL=egl`` before MuJoCo's first import)."""

    def __init__(self, world: int = 0, width: int = 320, height: int = 240, lookat=(0.35, 0.2, 0.15),
                 distance: float = 1.9, azimuth: float = 210.0, elevation: float = -28.0):
        self.world, self.size = world, (width, height)
        self.view = {"lookat": lookat, "distance": distance, "azimuth": azimuth, "elevation": elevation}
        self.frames: list[np.ndarray] = []
        self._renderer = None

    def __call__(self, twin, step: int) -> None:
        import mujoco

        if self._renderer is None:
            self._renderer = mujoco.Renderer(twin.mj_model, self.size[1], self.size[0])
            self._camera = mujoco.MjvCamera()
            self._camera.lookat[:] = self.view["lookat"]
            for key in ("distance", "azimuth", "elevation"):
                setattr(self._camera, key, self.view[key])
        self._renderer.update_scene(twin.data[self.world], camera=self._camera)
        self.frames.append(self._renderer.render().copy())


def save_strip(rows: list[tuple[str, list[np.ndarray]]], path, frames_per_row: int = 5) -> None:
    """One row per recording (its title and frames), ``frames_per_row`` frames evenly spaced from first to last."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(rows), frames_per_row, figsize=(2.4 * frames_per_row, 2.0 * len(rows)), squeeze=False)
    for r, (title, frames) in enumerate(rows):
        picks = np.linspace(0, len(frames) - 1, frames_per_row).round().astype(int)
        for c, i in enumerate(picks):
            ax = axes[r, c]
            ax.imshow(frames[i])
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"step {i}", fontsize=7)
        axes[r, 0].set_ylabel(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
