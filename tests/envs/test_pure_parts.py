"""Pure parts of envs/ on hand-made inputs: action adapter, projection, segmentation lookup, GL choice, task registry."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import envs
from envs import gl
from envs.actions import ActionAdapterConfig, ActionAdapterError, adapt_action
from envs.camera import project_points
from envs.segmentation import (
    ROBOT,
    TARGET,
    body_ancestry_matches,
    geom_categories,
    masks_from_segmentation,
    scene_lookup,
)

# ------------------------------------------------------------------ action adapter


def test_position_scaled_by_controller_limit_and_gripper_mapped():
    osc, clipped = adapt_action(np.array([0.02, -0.01, 0.05, 0, 0, 0, 1.0]))
    np.testing.assert_allclose(osc[:3], [0.4, -0.2, 1.0])
    np.testing.assert_allclose(osc[3:6], 0.0)
    assert osc[6] == -1.0  # Octo 1 = open -> robosuite -1 = open
    assert not clipped
    assert adapt_action(np.array([0, 0, 0, 0, 0, 0, 0.0]))[0][6] == 1.0  # closed
    assert adapt_action(np.array([0, 0, 0, 0, 0, 0, 0.25]))[0][6] == pytest.approx(0.5)


def test_position_clipped_per_component_and_counted():
    osc, clipped = adapt_action(np.array([0.2, -0.2, 0.01, 0, 0, 0, 1.0]))
    np.testing.assert_allclose(osc[:3], [1.0, -1.0, 0.2])
    assert clipped


def test_rotation_euler_to_axis_angle_and_scaled():
    config = ActionAdapterConfig()
    euler = np.array([0.1, -0.05, 0.2])
    osc, clipped = adapt_action(np.concatenate([[0, 0, 0], euler, [1.0]]), config)
    expected = Rotation.from_euler("xyz", euler).as_rotvec() / 0.5
    np.testing.assert_allclose(osc[3:6], expected, atol=1e-12)
    assert not clipped
    # a pure yaw is the same in every convention
    osc, _ = adapt_action(np.array([0, 0, 0, 0, 0, 0.3, 1.0]), ActionAdapterConfig(rotation_convention="rotvec"))
    np.testing.assert_allclose(osc[3:6], [0, 0, 0.6])


def test_large_rotation_keeps_axis_when_clipped():
    osc, clipped = adapt_action(np.array([0, 0, 0, 0.0, 0.0, 1.0, 1.0]))
    assert clipped
    np.testing.assert_allclose(osc[3:6], [0, 0, 1.0])
    osc, clipped = adapt_action(np.array([0, 0, 0, 0.6, 1.2, 0, 1.0]), ActionAdapterConfig(rotation_convention="rotvec"))
    np.testing.assert_allclose(osc[3:6], [0.5, 1.0, 0.0])


def test_gripper_conventions():
    binary = ActionAdapterConfig(gripper_mode="binary", gripper_threshold=0.6)
    assert adapt_action(np.array([0, 0, 0, 0, 0, 0, 0.7]), binary)[0][6] == -1.0
    assert adapt_action(np.array([0, 0, 0, 0, 0, 0, 0.5]), binary)[0][6] == 1.0
    flipped = ActionAdapterConfig(gripper_open_value=0.0)
    assert adapt_action(np.array([0, 0, 0, 0, 0, 0, 0.0]), flipped)[0][6] == -1.0
    osc, clipped = adapt_action(np.array([0, 0, 0, 0, 0, 0, 1.2]))
    assert osc[6] == -1.0 and clipped


def test_custom_scales():
    osc, _ = adapt_action(np.array([0.01, 0, 0, 0, 0, 0.1, 1.0]), ActionAdapterConfig(position_max=0.02, rotation_max=0.2))
    np.testing.assert_allclose(osc[[0, 5]], [0.5, 0.5])


def test_adapter_rejects_bad_input_with_one_line():
    with pytest.raises(ActionAdapterError, match="shape"):
        adapt_action(np.zeros(6))
    with pytest.raises(ActionAdapterError, match="NaN"):
        adapt_action(np.array([np.nan, 0, 0, 0, 0, 0, 1]))
    with pytest.raises(ActionAdapterError, match="rotation_convention"):
        ActionAdapterConfig(rotation_convention="quat")
    with pytest.raises(ActionAdapterError, match="gripper_mode"):
        ActionAdapterConfig(gripper_mode="soft")


# ------------------------------------------------------------------ projection


def test_projection_of_points_on_axis_and_off_axis():
    # camera at the origin looking along world -z (MuJoCo camera frame = world frame), fovy 90 degrees
    cam_pos, cam_xmat = np.zeros(3), np.eye(3)
    height = width = 100
    points = np.array(
        [
            [0.0, 0.0, -1.0],  # on the optical axis -> image centre
            [0.0, 1.0, -1.0],  # world +y = camera up -> top edge (tan 45 = 1)
            [0.5, 0.0, -1.0],  # camera right -> half way to the right edge
            [0.0, 0.0, 1.0],  # behind the camera
        ]
    )
    pixels = project_points(points, cam_pos, cam_xmat, 90.0, height, width)
    np.testing.assert_allclose(pixels[0], [49.5, 49.5])  # centre between pixels 49 and 50
    np.testing.assert_allclose(pixels[1], [-0.5, 49.5])  # top edge of the upright image
    np.testing.assert_allclose(pixels[2], [49.5, 74.5])
    assert np.all(np.isnan(pixels[3]))


def test_projection_with_translated_rotated_camera():
    # camera at (1, 0, 0) looking along world +x: camera z axis (backward) = world -x, camera y (up) = world z
    xmat = np.stack([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]], axis=1)  # columns: cam x, y, z in world
    pixels = project_points(np.array([[3.0, 0.0, 1.0]]), np.array([1.0, 0.0, 0.0]), xmat, 90.0, 64, 64)
    # 2 m ahead, 1 m up: half way to the top edge
    np.testing.assert_allclose(pixels[0], [32 - 16 - 0.5, 31.5])


# ------------------------------------------------------------------ segmentation lookup


def test_body_ancestry_and_geom_categories():
    # bodies: 0 world, 1 robot0_base, 2 robot0_link1 (child of 1), 3 gripper0_hand (child of 2), 4 cube_main, 5 table
    names = ["world", "robot0_base", "robot0_link1", "gripper0_hand", "cube_main", "table"]
    parents = np.array([0, 0, 1, 2, 0, 0])
    np.testing.assert_array_equal(body_ancestry_matches(names, parents, ("robot0_",)), [0, 1, 1, 1, 0, 0])
    geom_body = np.array([0, 1, 3, 4, 4, 5])
    categories = geom_categories(geom_body, names, parents, ("cube_",), ("robot0_",))
    np.testing.assert_array_equal(categories, [0, ROBOT, ROBOT, TARGET, TARGET, 0])


def test_masks_from_id_colours_through_scene_table():
    geom_category = np.array([0, ROBOT, TARGET, 0], dtype=np.uint8)  # model geoms 0..3
    # scene: segid 0 -> geom 3 (other), segid 1 -> geom 2 (target), segid 2 -> a site (objtype 6), segid 3 -> geom 1 (robot)
    segids, objtypes, objids = np.array([0, 1, 2, 3]), np.array([5, 5, 6, 5]), np.array([3, 2, 1, 1])
    table = scene_lookup(segids, objtypes, objids, geom_category)
    ids = np.array([[0, 1, 2], [3, 4, 300]])  # pixel id = segid + 1, 0 background, 300 out of range
    rgb = np.stack([ids & 255, (ids >> 8) & 255, (ids >> 16) & 255], axis=-1).astype(np.uint8)
    masks = masks_from_segmentation(rgb, table)
    np.testing.assert_array_equal(masks["target"], [[0, 0, 1], [0, 0, 0]])
    np.testing.assert_array_equal(masks["robot"], [[0, 0, 0], [0, 1, 0]])


# ------------------------------------------------------------------ headless GL choice


def test_backend_choice_respects_user_then_prefers_egl_then_osmesa():
    assert gl.choose_backend({"MUJOCO_GL": "OSMesa"}, lambda: True, lambda: True) == "osmesa"
    assert gl.choose_backend({}, lambda: True, lambda: True) == "egl"
    assert gl.choose_backend({}, lambda: False, lambda: True) == "osmesa"
    assert gl.choose_backend({}, lambda: False, lambda: False) == "egl"


def test_configure_fills_only_unset_variables(monkeypatch):
    environ = {"MUJOCO_GL": "osmesa"}
    assert gl.configure(environ) == "osmesa"
    assert environ == {"MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"}
    environ = {"MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl"}
    gl.configure(environ)
    assert environ == {"MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl"}


def test_gl_error_is_one_line_with_apt_fix():
    message = gl.error_message("egl", RuntimeError("Cannot initialize a EGL device display.\nmore"))
    assert "\n" not in message
    assert gl.APT_EGL in message and gl.APT_OSMESA in message and "MUJOCO_GL=osmesa" in message


# ------------------------------------------------------------------ task registry


def test_registry_lists_single_arm_tasks_with_instructions():
    tasks = envs.list_tasks()
    names = [task.name for task in tasks]
    for expected in ("Lift", "Stack", "PickPlaceCan", "PickPlaceMilk", "PickPlaceBread", "PickPlaceCereal", "NutAssemblySquare",
                     "NutAssemblyRound", "Door", "ToolHang", "Wipe"):
        assert expected in names
    assert len(set(names)) == len(names)
    for task in tasks:
        assert task.instruction and len(task.paraphrases) >= 2 and task.targets and task.max_episode_steps > 0
        assert task.instruction not in task.paraphrases


def test_unknown_task_error_lists_tasks_and_closest_match():
    with pytest.raises(envs.UnknownTaskError) as error:
        envs.get_task("PickPlaceCann")
    message = str(error.value)
    assert "\n" not in message and "'PickPlaceCan'" in message and "Lift" in message
    assert envs.get_task("lift").name == "Lift"


def test_every_task_registered_with_gymnasium():
    import gymnasium

    for task in envs.list_tasks():
        assert task.gym_id in gymnasium.registry


def test_task_table_has_a_row_per_task():
    lines = envs.task_table().splitlines()
    assert len(lines) == len(envs.list_tasks()) + 1
    assert lines[1].startswith("Lift") and "pick up the red cube" in lines[1]
