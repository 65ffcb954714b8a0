"""Offscreen camera rendering from a robosuite simulation: upright RGB frames and segmentation id images.

Renders through the simulation's own offscreen context (one GL context per environment), making that
context current before every render so that several environments in one process never draw each
other's scene. MuJoCo reads pixels bottom-up; every image returned here is flipped to upright
(row 0 = top), the orientation Octo was trained on. `fast` turns off reflections, shadows, the skybox
and 4x multisample anti-aliasing (robosuite's defaults), the expensive parts on a CPU (software)
rasteriser: about 4x faster per rendered frame (about 3x per env step, physics included: docs/benchmarks.md), with
no table reflections and harder edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CameraSpec:
    key: str  # observation key, e.g. "image_primary"
    camera: str  # MuJoCo camera name, e.g. "agentview"
    size: int  # square image side in pixels


class UnknownCameraError(ValueError):
    """A camera name the task's model does not have."""


class SceneRenderer:
    """Renders the given cameras of one simulation; use only from the thread that created the environment.

    Call `free()` before dropping the simulation: robosuite's context destructor frees MuJoCo's GL objects
    in whatever GL context happens to be current, which would delete another environment's textures.
    """

    def __init__(self, sim, cameras: tuple[CameraSpec, ...], fast: bool = False) -> None:
        self._sim = sim
        self._context = sim._render_context_offscreen  # robosuite MjRenderContextOffscreen, one per sim
        names = [sim.model.camera_id2name(i) for i in range(sim.model.ncam)]
        for spec in cameras:
            if spec.camera not in names:
                raise UnknownCameraError(f"camera {spec.camera!r} not in this task's model; available: {', '.join(names)}")
        self._camera_ids = {spec.key: names.index(spec.camera) for spec in cameras}
        self._sizes = {spec.key: spec.size for spec in cameras}
        if fast:
            import mujoco  # deferred: importing mujoco loads the GL backend (see envs.gl)

            flags = self._context.scn.flags
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
            flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
            flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0
            # no multisample anti-aliasing: the offscreen buffer is made at context creation, so remake it (unless
            # the simulation was built without it, as envs.robosuite_env builds it for fast rendering)
            if sim.model.vis.quality.offsamples != 0:
                self._context.gl_ctx.make_current()
                self._context.con.free()
                sim.model.vis.quality.offsamples = 0
                self._context._set_mujoco_context_and_buffers()

    def free(self) -> None:
        """Release this simulation's GL resources with its own context current (never another environment's)."""
        context, self._context = self._context, None
        if context is None:
            return
        context.gl_ctx.make_current()
        context.con.free()  # MuJoCo resets the struct, so robosuite's later __del__ frees nothing twice
        context.gl_ctx.free()

    def upload_texture(self, tex_id: int) -> None:
        """Send texture `tex_id` of the model to this simulation's GL context again (after its bitmap changed)."""
        import mujoco  # deferred: importing mujoco loads the GL backend (see envs.gl)

        self._context.gl_ctx.make_current()
        mujoco.mjr_uploadTexture(self._sim.model._model, self._context.con, tex_id)

    def camera_id(self, key: str) -> int:
        return self._camera_ids[key]

    def _render(self, key: str, segmentation: bool) -> np.ndarray:
        """(size, size, 3) uint8 upright pixels of camera `key`: colours, or id colours when `segmentation`."""
        import mujoco  # deferred: importing mujoco loads the GL backend (see envs.gl)

        size = self._sizes[key]
        context = self._context
        context.gl_ctx.make_current()
        context.render(size, size, camera_id=self._camera_ids[key], segmentation=segmentation)
        pixels = np.empty((size, size, 3), dtype=np.uint8)
        mujoco.mjr_readPixels(rgb=pixels, depth=None, viewport=mujoco.MjrRect(0, 0, size, size), con=context.con)
        return np.ascontiguousarray(pixels[::-1])

    def rgb(self, key: str) -> np.ndarray:
        """(size, size, 3) uint8 upright colour image of camera `key`."""
        return self._render(key, segmentation=False)

    def segmentation(self, key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Upright id-colour image (size, size, 3) uint8 and that scene's (segids, objtypes, objids), each (scene_geoms,)."""
        image = self._render(key, segmentation=True)
        scene = self._context.scn
        geoms = scene.geoms[: scene.ngeom]
        segids = np.fromiter((g.segid for g in geoms), dtype=np.int64, count=len(geoms))
        objtypes = np.fromiter((g.objtype for g in geoms), dtype=np.int64, count=len(geoms))
        objids = np.fromiter((g.objid for g in geoms), dtype=np.int64, count=len(geoms))
        return image, segids, objtypes, objids
