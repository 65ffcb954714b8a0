"""Environment options a run protocol records: masks, rendering, cameras, image convention, action space.

`EnvOptions` is frozen, hashable and round-trips through plain JSON/TOML data (`to_dict` / `from_dict`),
so a run manifest can embed it and a protocol file can hold it. Parsed once at the edge:

    EnvOptions(cameras=(("image_primary", "agentview", 84),), action_space="robosuite")
    EnvOptions.from_dict({"cameras": {"image_primary": ["agentview", 84]}, "image_convention": "opengl"})
    parse_camera("image_primary=agentview:84")  ->  ("image_primary", "agentview", 84)

Fields:
  masks            target/robot masks in `info` every step (attention mass on the target).
  fast_render      no shadows, reflections, skybox or anti-aliasing (on a CPU: about 4x faster per rendered
                   frame, about 3x per env step).
  cameras          ((observation key, robosuite camera, square size), ...) in observation order;
                   None = the task's defaults (image_primary = agentview 256, image_wrist = eye-in-hand 128).
  image_convention "upright" (row 0 = top, what Octo's datasets hold) or "opengl" (row 0 = bottom: frames
                   stored upside down, as robosuite renders them and robomimic datasets store them) or
                   "rot180" (the rendered frame turned 180 degrees = upright mirrored left to right: OpenVLA's
                   LIBERO datasets, which Octo's LIBERO finetunes were trained on). It applies to every
                   pixel-indexed thing the env returns: images, masks, target pixels.
  action_space     "octo-delta": Octo's 7-D end-effector delta (Bridge convention, see envs.actions);
                   "robosuite": the controller's own 7-D input (OSC_POSE delta: 6 arm values in [-1, 1],
                   gripper -1 open / +1 closed), as robosuite and robomimic datasets store actions;
                   "libero": OpenVLA's LIBERO datasets' convention (6 OSC_POSE values in [-1, 1], gripper
                   1 open / 0 closed, binarised at 0.5 as OpenVLA's evaluation does; envs.actions.libero_action).
  hold_gripper     None, or the gripper value held at every step for a model without a gripper dimension (6-D
                   arm-only actions): the env then takes 6-D actions and appends it. Given as "open", "closed"
                   or a number in the action space's own units (octo-delta: 1 open, 0 closed; robosuite: -1 open,
                   +1 closed), recorded as that number.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from envs import suites as _suites

IMAGE_CONVENTIONS = ("upright", "opengl", "rot180")
ACTION_SPACES = ("octo-delta", "robosuite", "libero")
# the gripper value of "open" / "closed" and its range, per action space
GRIPPER_VALUES = {"octo-delta": {"open": 1.0, "closed": 0.0, "range": (0.0, 1.0)},
                  "robosuite": {"open": -1.0, "closed": 1.0, "range": (-1.0, 1.0)},
                  "libero": {"open": 1.0, "closed": 0.0, "range": (0.0, 1.0)}}
# what each action space's actions look like in a dataset's statistics: (translation, gripper range), the pre-flight
# check's evidence (harness.run.preflight): metres per step or a controller input in [-1, 1]; the gripper's ends
ACTION_SPACE_UNITS = {"octo-delta": ("metres", "0..1"), "robosuite": ("controller", "-1..1"),
                      "libero": ("controller", "0..1")}

# the built-in suites' default conventions, for a key neither the command line nor the checkpoint's harness.toml sets,
# and their names as the help and the docs word them: each suite declares its own (envs.suites.Suite.defaults, title;
# harness.conventions.resolve_env applies the suite of a task's), and the --help and the docs' option table word the
# built-in ones from here
FAMILY_DEFAULTS = {cls.name: dict(cls.defaults) for cls in _suites.builtin()}
FAMILY_NAMES = {cls.name: cls.title for cls in _suites.builtin()}


def family_defaults_text(key: str, harness_toml: str = "harness.toml") -> str:
    """The default of convention `key` in words, from FAMILY_DEFAULTS: "the checkpoint's harness.toml, else the task
    family's: robosuite upright, LIBERO rot180"."""
    families = ", ".join(f"{FAMILY_NAMES[f]} {d[key]}" for f, d in FAMILY_DEFAULTS.items())
    return f"the checkpoint's {harness_toml}, else the task family's: {families}"


_CAMERA_SPEC = re.compile(r"^([A-Za-z_][\w]*)=([^:=\s]+):(\d+)$")


class EnvConfigError(ValueError):
    """Invalid environment options (message: one line naming the fix)."""


def to_convention(image: np.ndarray, convention: str) -> np.ndarray:
    """(height, width, ...) upright pixels -> the same in `convention` ("opengl": rows reversed; "rot180": the
    rendered (opengl) frame turned 180 degrees, i.e. columns reversed). Its own inverse."""
    if convention == "opengl":
        return np.ascontiguousarray(np.asarray(image)[::-1])
    if convention == "rot180":
        return np.ascontiguousarray(np.asarray(image)[:, ::-1])
    if convention == "upright":
        return image
    raise EnvConfigError(f"image convention {convention!r} unknown; use one of {', '.join(IMAGE_CONVENTIONS)}")


MAX_CAMERA_SIZE = 2048  # px per side: rendered, masked and stored at every step


def parse_camera(text: str) -> tuple[str, str, int]:
    """"KEY=camera:size" (e.g. "image_primary=agentview:84") -> (key, camera, size), size 1..MAX_CAMERA_SIZE."""
    match = _CAMERA_SPEC.match(text.strip())
    if not match or int(match.group(3)) <= 0:
        raise EnvConfigError(f"camera {text!r}: expected KEY=camera:size with a positive size, e.g. image_primary=agentview:84")
    if int(match.group(3)) > MAX_CAMERA_SIZE:
        raise EnvConfigError(f"camera {text!r}: size {int(match.group(3))} is larger than {MAX_CAMERA_SIZE} px; choose "
                             f"a size up to {MAX_CAMERA_SIZE}, e.g. {match.group(1)}={match.group(2)}:256")
    return match.group(1), match.group(2), int(match.group(3))


def _camera_tuple(cameras: Any) -> tuple[tuple[str, str, int], ...] | None:
    """Cameras as given (None, {key: (camera, size)}, [(key, camera, size)], ["KEY=camera:size"]) -> canonical tuple."""
    if cameras is None:
        return None
    if isinstance(cameras, Mapping):
        items = []
        for key, value in cameras.items():
            if isinstance(value, str):  # {key: "camera:size"}
                items.append(parse_camera(f"{key}={value}"))
                continue
            if not (isinstance(value, (tuple, list)) and len(value) == 2):
                raise EnvConfigError(f"camera {key!r}: expected (robosuite camera name, size), got {value!r}")
            items.append((key, value[0], value[1]))
    else:
        items = [parse_camera(c) if isinstance(c, str) else tuple(c) for c in cameras]
    out = []
    for item in items:
        if len(item) != 3:
            raise EnvConfigError(f"camera {item!r}: expected (observation key, robosuite camera, size)")
        key, camera, size = item
        if isinstance(size, bool) or not isinstance(size, int) or size <= 0:
            raise EnvConfigError(f"camera {key!r}: size must be a positive integer, got {size!r}")
        if size > MAX_CAMERA_SIZE:
            raise EnvConfigError(f"camera {key!r}: size {size} is larger than {MAX_CAMERA_SIZE} px (a {size}x{size} "
                                 f"frame per step); choose a size up to {MAX_CAMERA_SIZE}, e.g. {key}={camera}:256")
        if key == "proprio":
            raise EnvConfigError("camera key 'proprio' is reserved for the proprioceptive state; choose another key")
        out.append((str(key), str(camera), int(size)))
    keys = [k for k, _, _ in out]
    if len(set(keys)) != len(keys):
        raise EnvConfigError(f"camera keys repeat: {keys}; give each observation key one camera")
    return tuple(out)


def _gripper_value(value: Any, action_space: str) -> float:
    """"open" | "closed" | a number (also as text) -> the gripper value in `action_space`'s units, range-checked."""
    values = GRIPPER_VALUES[action_space]
    low, high = values["range"]
    if isinstance(value, str) and value.strip().lower() in ("open", "closed"):
        return values[value.strip().lower()]
    try:
        number = float(value) if not isinstance(value, bool) else float("nan")
    except (TypeError, ValueError):
        number = float("nan")
    if not low <= number <= high:
        raise EnvConfigError(f"--hold-gripper {value!r}: use open, closed or a number in [{low:g}, {high:g}] "
                             f"(the {action_space} action space: open = {values['open']:g}, closed = {values['closed']:g})")
    return number


@dataclass(frozen=True)
class EnvOptions:
    # The command line's options (metadata "option": harness.options.Option's fields as a plain dict, as envs/ sits
    # below harness/; a run resolves them: flags over the checkpoint's harness.toml over the task family's defaults)
    masks: bool = field(default=False, metadata={"option": dict(
        flag="--no-masks", help="do not render target/robot masks", file=(bool,), action="store_true", negated=True,
        absent=True)})  # a run's masks are on; the env's own default (envs.make) is off
    fast_render: bool = field(default=False, metadata={"option": dict(
        flag="--fast-render", help={"run": "render without reflections, shadows and anti-aliasing (about 3x faster per "
                                           "env step: docs/benchmarks.md; about 4x per rendered frame)",
                                    "robustness": "as for `run --fast-render`"},
        file=(bool,), action="store_true", convert=bool)})
    # None: the task's default cameras; () renders nothing
    cameras: tuple[tuple[str, str, int], ...] | None = field(default=None, metadata={"option": dict(
        flag="--camera", help="observation key fed by a robosuite camera at a square size, e.g. "
        "image_primary=agentview:84 (repeat; default: the checkpoint's harness.toml, else the task's cameras)",
        file=(str, list, dict), action="append", metavar="KEY=camera:size", field="cameras",
        convert=lambda v: tuple(parse_camera(c) for c in v) or None,
        doc="observation key fed by a robosuite camera at a square size (repeat); default: the checkpoint's "
            "`harness.toml`, else the task family's (robosuite: the task's cameras; LIBERO: the published protocol); "
            "the manifest's `conventions` says which")})
    image_convention: str = field(default=FAMILY_DEFAULTS["robosuite"]["image_convention"], metadata={"option": dict(
        flag="--image-convention", help="orientation of the frames the model was trained on (rot180: OpenVLA's LIBERO "
        "datasets)", default_text=family_defaults_text("image_convention"), file=(str,), choices=IMAGE_CONVENTIONS,
        doc="orientation of the frames the model was trained on (rot180: OpenVLA's LIBERO datasets) "
            f"[{family_defaults_text('image_convention', '`harness.toml`')}]")})
    action_space: str = field(default=FAMILY_DEFAULTS["robosuite"]["action_space"], metadata={"option": dict(
        flag="--action-space", help="what the model's actions mean", default_text=family_defaults_text("action_space"),
        file=(str,), choices=ACTION_SPACES,
        doc=f"what the model's actions mean [{family_defaults_text('action_space', '`harness.toml`')}]")})
    # gripper value held for 6-D (arm-only) models; the env then takes 6-D actions
    hold_gripper: float | None = field(default=None, metadata={"option": dict(
        flag="--hold-gripper", help="for a 6-D (arm-only) model: the env takes 6-D actions and holds the gripper at "
        "this value (octo-delta: 1 open, 0 closed; robosuite: -1 open, +1 closed); part of the protocol",
        file=(str, int, float), metavar="open|closed|VALUE", sparse=True,
        doc="a 6-D (arm-only) model: the env takes the 6 arm values and holds the gripper at this value (octo-delta: "
            "1 open, 0 closed; robosuite: -1 open, +1 closed); without it such a model is refused with a line naming "
            "this option")})

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", _camera_tuple(self.cameras))
        if self.image_convention not in IMAGE_CONVENTIONS:
            raise EnvConfigError(f"image convention {self.image_convention!r} unknown; use one of {', '.join(IMAGE_CONVENTIONS)}")
        if self.action_space not in ACTION_SPACES:
            raise EnvConfigError(f"action space {self.action_space!r} unknown; use one of {', '.join(ACTION_SPACES)}")
        if self.masks and self.cameras == ():
            raise EnvConfigError("masks need at least one camera; add --camera KEY=camera:size or turn masks off")
        if self.hold_gripper is not None:
            object.__setattr__(self, "hold_gripper", _gripper_value(self.hold_gripper, self.action_space))

    @property
    def camera_dict(self) -> dict[str, tuple[str, int]] | None:
        """{observation key: (robosuite camera, size)}, or None for the task's defaults."""
        return None if self.cameras is None else {k: (c, s) for k, c, s in self.cameras}

    def to_dict(self) -> dict:
        """Plain JSON/TOML data; cameras as {key: [camera, size]} (None when the task's defaults are used)."""
        cameras = None if self.cameras is None else {k: [c, s] for k, c, s in self.cameras}
        held = {} if self.hold_gripper is None else {"hold_gripper": self.hold_gripper}  # only when set: hashes stay
        return {"masks": self.masks, "fast_render": self.fast_render, "cameras": cameras,
                "image_convention": self.image_convention, "action_space": self.action_space, **held}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "EnvOptions":
        """Inverse of `to_dict`; unknown keys raise (a typo in a protocol file must not be ignored)."""
        known = {"masks", "fast_render", "cameras", "image_convention", "action_space", "hold_gripper"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise EnvConfigError(f"unknown env option(s) {unknown}; known: {sorted(known)}")
        return cls(**dict(data))

    def replace(self, **changes) -> "EnvOptions":
        """A copy with some fields changed (None values are ignored: 'not given on the command line')."""
        return EnvOptions(**{**self.to_dict(), **{k: v for k, v in changes.items() if v is not None}})
