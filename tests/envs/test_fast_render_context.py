"""--fast-render's offscreen context is made once, without multisampling (envs.robosuite_env builds the simulation
that way before robosuite makes the context), and draws exactly what robosuite's multisampled context freed and made
again without multisampling drew (the way it was made before: envs.render.SceneRenderer(fast=True) remaking it).
Real robosuite and real headless rendering, no mocks."""

import numpy as np

import envs
from envs.render import SceneRenderer

CAMERAS = {"image_primary": ("agentview", 64), "image_wrist": ("robot0_eye_in_hand", 32)}


def test_fast_render_context_is_made_single_sampled_and_draws_as_a_remade_one():
    fast = envs.make("Lift", cameras=CAMERAS, masks=True, fast_render=True)
    plain = envs.make("Lift", cameras=CAMERAS, masks=True)
    try:
        assert fast._env.sim.model.vis.quality.offsamples == 0
        assert type(fast._env).__name__ == "Lift"  # as robosuite and messages name it
        assert plain._env.sim.model.vis.quality.offsamples == 4  # MuJoCo's default: robosuite's context multisamples
        fast_obs, fast_info = fast.reset(seed=3)
        plain.reset(seed=3)
        # plain's context, freed and made again without multisampling, with fast rendering's flags
        remade = SceneRenderer(plain._env.sim, plain.config.cameras, fast=True)
        assert plain._env.sim.model.vis.quality.offsamples == 0
        for spec in plain.config.cameras:
            np.testing.assert_array_equal(fast._renderer.rgb(spec.key), remade.rgb(spec.key))
            np.testing.assert_array_equal(fast_obs[spec.key], remade.rgb(spec.key))
            image, *scene = remade.segmentation(spec.key)
            fast_image, *fast_scene = fast._renderer.segmentation(spec.key)
            np.testing.assert_array_equal(fast_image, image)
    finally:
        fast.close()
        plain.close()
