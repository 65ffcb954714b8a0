"""Controlled perturbations of a robosuite scene: data parsed once, drawn per episode, applied with robosuite's modders.

A perturbation is data: `Perturbation(kind, level, camera)` with level 0 (nominal) .. 5 (severe), written
`KIND[@KEY]:LEVEL` (`camera:3`, `camera@image_wrist:2`, `noise@image_primary:4`, `lighting:1`). Several are
comma-separated. Level-0 entries are dropped when parsed: a protocol whose perturbations are all at level 0 IS the
nominal protocol (same protocol hash, same run folder, same frames bit for bit).

Kinds and what one level means: docs/perturbations.md's table, whose numbers are MAGNITUDES here; each `Kind`
subclass below says what it changes and which of robosuite's modders it uses.

Draws: every random choice of an episode comes from `numpy.random.SeedSequence((reset seed, kind, level, key))`,
where the kind is its number in `KIND_SEEDS` (or, for a kind not listed there, drawn from its name), never its
position in the table, and the reset seed is the episode's seed (protocol seed + episode index), never from the simulator's own
random stream: the scene's nominal randomness (object placement, robosuite's joint noise) is the nominal
episode's, so a perturbed episode pairs with the nominal episode of the same seed, and the same protocol gives
the same scene and frames whatever ran before, in whichever process. Scene modding happens at reset only
(sensor noise excepted).
"""

from __future__ import annotations

import re
import zlib
from dataclasses import dataclass

import numpy as np

from envs.scene_edits import (DISTRACTOR_PREFIX, NO_DISTRACTOR_ROOM, TEXTURE_PATTERNS, PerturbationError, distractor_region,
                              material_texture, perturbed_camera, place_distractors, rotate, texture_pattern,
                              uniform_samplers, unit_vector)

LEVELS = tuple(range(6))
DEFAULT_CAMERA_KEY = "image_primary"
# KINDS (names in order) and KEYED_KINDS (those that take @KEY, an observation key) come from the table of kind
# classes, KIND_TABLE, at the end of this module

# physical magnitude of one level, per kind (multiplied by the level)
MAGNITUDES = {
    "camera": {"position_m": 0.02, "rotation_deg": 2.0, "fovy_deg": 1.0},
    "lighting": {"intensity_drop": 0.12, "direction_deg": 5.0, "tint": 0.04},
    "texture": {"blend": 0.2},
    "distractors": {"objects": 1, "clearance_m": 0.10, "spacing_m": 0.07},
    "init-state": {"joint_rad": 0.03, "placement_m": 0.02},
    "noise": {"blur_sigma_px": 0.25, "gaussian_sigma": 3.0, "jpeg_quality_drop": 14},
    "language": {},
}
LANGUAGE_LEVELS = {1: "capitalised, full stop", 2: "a paraphrase from the task's list",
                   3: "paraphrase after a prefix", 4: "paraphrase with a prefix and a suffix",
                   5: "level 4 in capitals"}
PREFIXES = ("please ", "robot, ", "now ")
SUFFIXES = (" now", " please", ", thanks")
_SPEC = re.compile(r"^([a-z-]+)(?:@([A-Za-z_]\w*))?:(-?\d+)$")


@dataclass(frozen=True, order=True)
class Perturbation:
    kind: str
    level: int
    camera: str | None = None  # observation key (camera: default image_primary; noise: None = every camera)

    @property
    def label(self) -> str:
        return f"{self.kind}{'@' + self.camera if self.camera else ''}:{self.level}"

    @property
    def condition(self) -> str:
        """The condition without its level (`camera@image_primary`), as a robustness grid groups runs."""
        return f"{self.kind}{'@' + self.camera if self.camera else ''}"


def _cut(value, limit: int = 200) -> str:
    """repr of a value given on the command line, cut to about `limit` characters (a 50 MB value is not echoed)."""
    text = repr(value[: limit + 1] if isinstance(value, str) else value)
    return text if len(text) <= limit else f"{text[:limit - 3]}... ({len(value) if isinstance(value, str) else '?'} characters)"


def parse_perturb(value) -> tuple[Perturbation, ...]:
    """"KIND[@KEY]:LEVEL[,...]" (or a list of them, or None) -> canonical perturbations, level 0 dropped, sorted.

    One-line errors for an unknown kind, a level outside 0-5, @KEY on a kind without a key, a repeated kind.
    """
    if value is None:
        return ()
    items = value if isinstance(value, (list, tuple)) else [value]
    texts = [t.strip() for item in items for t in str(item).split(",") if t.strip()]
    if not texts:  # "" or ",,,": no perturbation named (robustness refuses the same); nominal is no --perturb at all
        raise PerturbationError(f"--perturb {_cut(value)} names no perturbation; pass KIND[@KEY]:LEVEL (e.g. camera:3), "
                                "or leave --perturb out for the nominal scene")
    out: dict[tuple[str, str | None], Perturbation] = {}
    for text in texts:
        match = _SPEC.match(text)
        if not match:
            raise PerturbationError(f"--perturb {_cut(text)}: expected KIND[@KEY]:LEVEL, e.g. camera:3, camera@image_wrist:2, "
                                    f"lighting:1 (kinds: {', '.join(KINDS)}; levels 0-5)")
        kind, key, level = match.group(1), match.group(2), int(match.group(3))
        if kind not in KINDS:
            raise PerturbationError(f"--perturb {_cut(text)}: unknown kind {kind!r}; kinds: {', '.join(KINDS)}")
        if level not in LEVELS:
            raise PerturbationError(f"--perturb {_cut(text)}: level must be 0 (nominal) to 5 (severe), got {level}")
        if key is not None and kind not in KEYED_KINDS:
            raise PerturbationError(f"--perturb {_cut(text)}: only {' and '.join(KEYED_KINDS)} take @KEY; write {kind}:{level}")
        if kind == "camera" and key is None:
            key = DEFAULT_CAMERA_KEY
        if (kind, key) in out or (kind == "noise" and any(k == "noise" and (key is None or c is None) for k, c in out)):
            raise PerturbationError(f"--perturb: {kind}{'@' + key if key else ''} is given twice; give each kind (and key) once")
        out[(kind, key)] = Perturbation(kind, level, key)
    kept = [p for p in out.values() if p.level > 0]
    return tuple(sorted(kept, key=lambda p: (KINDS.index(p.kind), p.camera or "")))


def perturb_text(perturbations: tuple[Perturbation, ...]) -> str | None:
    """Canonical text of perturbations (what a protocol records), None for the nominal scene."""
    return ",".join(p.label for p in perturbations) or None


def find(perturbations: tuple[Perturbation, ...], kind: str) -> list[Perturbation]:
    return [p for p in perturbations if p.kind == kind]


def check_task(task, perturbations: tuple[Perturbation, ...], camera_keys: tuple[str, ...],
               instruction_override: str | None = None) -> None:
    """Whether `task` (envs.taskspec.TaskSpec) with cameras `camera_keys` can take the perturbations: one line if not."""
    for p in perturbations:
        kind = KIND_TABLE[p.kind]
        if kind.keyed and p.camera is not None and p.camera not in camera_keys:
            raise PerturbationError(f"--perturb {p.label}: task {task.name} has no camera {p.camera!r} (its cameras: "
                                    f"{', '.join(camera_keys) or 'none'}); use {p.kind}@KEY with one of them")
        kind.check(task, p, instruction_override)
        if kind.visual and not camera_keys:
            raise PerturbationError(f"--perturb {p.label}: the env renders no camera, so a visual perturbation changes "
                                    "nothing; add a camera or drop it")


# ---------------------------------------------------------------------------------------------- draws

# The number each kind puts in its draws' seeds. These are the kinds' positions in KIND_TABLE when the seed was
# still the position; frozen here, so that their draws stay the same whatever is later inserted into the table.
KIND_SEEDS = {"camera": 0, "lighting": 1, "texture": 2, "distractors": 3, "init-state": 4, "noise": 5, "language": 6}


def kind_seed(kind: str) -> int:
    """The kind's number in its draws' seeds: its frozen one, or for a newer kind a number drawn from its name."""
    return KIND_SEEDS[kind] if kind in KIND_SEEDS else zlib.crc32(f"perturbation kind {kind}".encode())


def rng(seed: int, p: Perturbation, *extra: int) -> np.random.Generator:
    """The generator of one draw: SeedSequence((seed, kind, level, key, *extra)); independent of every other stream."""
    key = zlib.crc32((p.camera or "").encode())
    return np.random.default_rng(np.random.SeedSequence([int(seed), kind_seed(p.kind), int(p.level), key, *extra]))


def camera_draw(seed: int, p: Perturbation) -> dict:
    """{"offset": (3,) m in the camera's parent frame, "axis": (3,) in the camera frame, "degrees", "fovy_delta"}."""
    g = rng(seed, p)
    m = MAGNITUDES["camera"]
    offset = unit_vector(g) * m["position_m"] * p.level
    axis = unit_vector(g)
    fovy = float(np.sign(g.uniform(-1, 1)) or 1.0) * m["fovy_deg"] * p.level
    return {"offset": offset, "axis": axis, "degrees": m["rotation_deg"] * p.level, "fovy_delta": fovy}


def lighting_draw(seed: int, p: Perturbation, lights: int) -> dict:
    g = rng(seed, p)
    m = MAGNITUDES["lighting"]
    axes = []
    for _ in range(lights):
        a = g.normal(size=2)
        axes.append(np.array([a[0], a[1], 0.0]) / np.linalg.norm(a))
    tint = 1.0 + g.uniform(-1, 1, size=(lights, 3)) * m["tint"] * p.level
    return {"scale": 1.0 - m["intensity_drop"] * p.level, "axes": axes, "degrees": m["direction_deg"] * p.level,
            "tint": tint}


def instruction_for(task, instruction: str, seed: int, perturbations: tuple[Perturbation, ...]) -> str:
    """The episode's instruction: `instruction` unless a language perturbation rewrites it (see the module docstring)."""
    found = find(perturbations, "language")
    if not found:
        return instruction
    p = found[0]
    g = rng(seed, p)
    if p.level == 1:
        return instruction[:1].upper() + instruction[1:] + "."
    text = task.paraphrases[int(g.integers(len(task.paraphrases)))]
    if p.level >= 3:
        text = PREFIXES[int(g.integers(len(PREFIXES)))] + text
    if p.level >= 4:
        text = text + SUFFIXES[int(g.integers(len(SUFFIXES)))]
    if p.level >= 5:
        text = text.upper()
    return text


def noise_frame(frame: np.ndarray, seed: int, p: Perturbation, step: int, key: str) -> np.ndarray:
    """(h, w, 3) uint8 -> the frame after blur, Gaussian noise and JPEG at `p.level` (drawn per step and camera)."""
    import cv2

    m = MAGNITUDES["noise"]
    out = np.asarray(frame)
    sigma = m["blur_sigma_px"] * p.level
    out = cv2.GaussianBlur(out, (0, 0), sigmaX=sigma, sigmaY=sigma)
    g = np.random.default_rng(np.random.SeedSequence([int(seed), kind_seed("noise"), p.level, zlib.crc32(key.encode()),
                                                      int(step)]))
    noisy = out.astype(np.float32) + g.normal(0.0, m["gaussian_sigma"] * p.level, size=out.shape).astype(np.float32)
    out = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    quality = int(90 - m["jpeg_quality_drop"] * p.level)
    ok, encoded = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return np.ascontiguousarray(cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED).reshape(out.shape))


# ---------------------------------------------------------------------------------------------- the env side

class ScenePerturber:
    """Applies one protocol's perturbations to one robosuite env at every reset (and to frames, for noise).

    env: the robosuite env (built with `class_with_distractors` when distractors are asked for); cameras: {obs key:
    robosuite camera name}; upload(tex_id): re-uploads a changed texture to the env's GL context.
    Nominal values are saved once, at construction (each kind's `setup`), and restored before every episode's draw,
    so an episode's scene depends on its own seed only. Kinds act in the table's order (KIND_TABLE), each entry of a
    kind in the order given.
    """

    def __init__(self, env, perturbations: tuple[Perturbation, ...], cameras: dict[str, str], upload=None,
                 target_geoms: tuple = ()):
        self.env = env
        self.perturbations = perturbations
        self.cameras = cameras
        self.upload = upload
        self.target_geoms = target_geoms
        self.record: dict = {}
        self._active = [(kind, p, kind.setup(self, p)) for kind in KIND_TABLE.values()
                        for p in find(perturbations, kind.name)]

    def before_reset(self, seed: int) -> None:
        """Perturbations robosuite's own reset must see: the robot's initial joints and the placement ranges."""
        for kind, p, state in self._active:
            kind.before_reset(self, p, state, seed)

    def after_reset(self, seed: int, avoid_xy: np.ndarray) -> None:
        """Camera, lighting, texture and distractor placement of this episode; then the simulation is forwarded."""
        for kind, p, state in self._active:
            kind.after_reset(self, p, state, seed, avoid_xy)
        self.env.sim.forward()

    def noisy(self, frames: dict[str, np.ndarray], seed: int, step: int) -> dict[str, np.ndarray]:
        """{obs key: upright frame} -> the frames the policy sees (sensor noise on the chosen cameras)."""
        for kind, p, state in self._active:
            frames = kind.frames(p, state, frames, seed, step)
        return frames

    def bitmap(self, tex: int) -> np.ndarray:
        """(h, w, channels) uint8 view of texture `tex` in the model."""
        model = self.env.sim.model
        h, w, c = int(model.tex_height[tex]), int(model.tex_width[tex]), int(model.tex_nchannel[tex])
        adr = int(model.tex_adr[tex])
        return model.tex_data[adr: adr + h * w * c].reshape(h, w, c)


# ---------------------------------------------------------------------------------------------- the kinds

class Kind:
    """One perturbation kind. `check` refuses what a task cannot take (one line); `setup` saves the nominal values
    one env needs (its state, kept by the ScenePerturber); `before_reset` / `after_reset` mod the scene around
    robosuite's reset (each writes what it drew into `perturber.record`); `frames` changes what the policy sees at a
    step. A new kind is one subclass and one row of KIND_TABLE (docs/perturbations.md lists them; tests check it)."""

    name = ""
    keyed = False  # takes @KEY (an observation key)
    visual = True  # changes what a camera sees: refused when the env renders no camera

    def check(self, task, p: Perturbation, instruction_override: str | None) -> None:
        return None

    def setup(self, perturber: ScenePerturber, p: Perturbation):
        return None

    def before_reset(self, perturber: ScenePerturber, p: Perturbation, state, seed: int) -> None:
        return None

    def after_reset(self, perturber: ScenePerturber, p: Perturbation, state, seed: int, avoid_xy: np.ndarray) -> None:
        return None

    def frames(self, p: Perturbation, state, frames: dict[str, np.ndarray], seed: int, step: int) -> dict[str, np.ndarray]:
        return frames


class CameraKind(Kind):
    """The camera behind an observation key moved, turned and its field of view changed (robosuite's CameraModder)."""

    name, keyed = "camera", True

    def setup(self, perturber, p):
        from robosuite.utils.mjmod import CameraModder

        name = perturber.cameras[p.camera]
        return name, CameraModder(perturber.env.sim, random_state=np.random.RandomState(0), camera_names=[name])

    def after_reset(self, perturber, p, state, seed, avoid_xy):
        name, modder = state
        modder.restore_defaults()
        draw = camera_draw(seed, p)
        d = modder._defaults[name]
        pos, quat, fovy = perturbed_camera(d["pos"], d["quat"], d["fovy"], draw)
        modder.set_pos(name, pos)
        modder.set_quat(name, quat)
        modder.set_fovy(name, fovy)
        perturber.record[p.condition] = {"camera": name, "offset_m": draw["offset"].round(6).tolist(),
                                         "axis": draw["axis"].round(6).tolist(), "degrees": draw["degrees"],
                                         "fovy_deg": fovy}


class LightingKind(Kind):
    """Every light darker, turned and tinted, and the headlight darker (robosuite's LightingModder)."""

    name = "lighting"

    def setup(self, perturber, p):
        from robosuite.utils.mjmod import LightingModder

        model = perturber.env.sim.model
        return (LightingModder(perturber.env.sim, random_state=np.random.RandomState(0),
                               light_names=list(model.light_names)),
                np.array(model.vis.headlight.ambient), np.array(model.vis.headlight.diffuse))

    def after_reset(self, perturber, p, state, seed, avoid_xy):
        modder, ambient, diffuse = state
        modder.restore_defaults()
        draw = lighting_draw(seed, p, len(modder.light_names))
        for i, name in enumerate(modder.light_names):
            d = modder._defaults[name]
            modder.set_diffuse(name, np.clip(d["diffuse"] * draw["scale"] * draw["tint"][i], 0, 1))
            modder.set_ambient(name, d["ambient"] * draw["scale"])
            modder.set_specular(name, d["specular"] * draw["scale"])
            modder.set_dir(name, rotate(d["dir"], draw["axes"][i], draw["degrees"]))
        headlight = perturber.env.sim.model.vis.headlight
        headlight.ambient[:] = ambient * draw["scale"]
        headlight.diffuse[:] = diffuse * draw["scale"]
        perturber.record["lighting"] = {"scale": draw["scale"], "degrees": draw["degrees"],
                                        "tint": np.round(draw["tint"], 6).tolist()}


class TextureKind(Kind):
    """The arena's textures and untextured geoms blended with a drawn pattern (never an object, the robot, the target)."""

    name = "texture"

    def setup(self, perturber, p):
        """(textures {tex id: nominal (h, w, c) uint8}, untextured arena geoms {geom id: nominal rgba}).

        robosuite 1.5.2's TextureModder reads `MjModel.tex_rgb`, which MuJoCo 3 renamed `tex_data`; so textures are
        blended here, in the same way (default bitmap blended with a drawn pattern), on `tex_data`."""
        from envs.segmentation import body_ancestry_matches

        env = perturber.env
        model = env.sim.model
        names = [model.body_id2name(i) or "" for i in range(model.nbody)]
        prefixes = tuple(obj.name + "_" for obj in getattr(env.model, "mujoco_objects", ())) + \
            ("robot0_", "gripper0_", "mount0_", "fixed_mount0_", DISTRACTOR_PREFIX)
        foreign_body = body_ancestry_matches(names, model.body_parentid, prefixes)
        targets = {int(i) for ids in perturber.target_geoms for i in np.asarray(ids).ravel()}
        arena, used_elsewhere = [], set()
        for g in range(model.ngeom):
            name = model.geom_id2name(g) or ""
            tex = material_texture(model, int(model.geom_matid[g]))
            if foreign_body[model.geom_bodyid[g]] or g in targets:
                if tex >= 0:
                    used_elsewhere.add(tex)
                continue
            if "eef_target" not in name and int(model.geom_group[g]) == 1:
                arena.append((g, tex))
        textures = {tex: perturber.bitmap(tex).copy() for g, tex in arena if tex >= 0 and tex not in used_elsewhere}
        plain = {g: np.array(model.geom_rgba[g]) for g, tex in arena if tex < 0}
        return textures, plain

    def after_reset(self, perturber, p, state, seed, avoid_xy):
        textures, plain = state
        g = rng(seed, p)
        blend = MAGNITUDES["texture"]["blend"] * p.level
        chosen = {}
        for tex, nominal in textures.items():
            variation = TEXTURE_PATTERNS[int(g.integers(len(TEXTURE_PATTERNS)))]
            pattern = texture_pattern(g, variation, nominal.shape)
            blended = (1.0 - blend) * nominal.astype(np.float64) + blend * pattern
            perturber.bitmap(tex)[:] = np.clip(np.rint(blended), 0, 255).astype(np.uint8)
            chosen[str(tex)] = variation
            if perturber.upload is not None:
                perturber.upload(tex)
        model = perturber.env.sim.model
        for geom, rgba in plain.items():
            colour = g.uniform(0, 1, size=3)
            model.geom_rgba[geom, :3] = (1 - blend) * rgba[:3] + blend * colour
        perturber.record["texture"] = {"blend": blend, "textures": chosen, "plain_geoms": len(plain)}


class DistractorsKind(Kind):
    """`level` extra objects placed on the task's free surface, clear of the task's objects."""

    name = "distractors"

    def check(self, task, p, instruction_override):
        if task.name in NO_DISTRACTOR_ROOM:
            raise PerturbationError(f"--perturb {p.label}: task {task.name} cannot take distractors "
                                    f"({NO_DISTRACTOR_ROOM[task.name]}); drop distractors or the task")

    def setup(self, perturber, p):
        return getattr(perturber.env, "_octo_distractors", [])

    def after_reset(self, perturber, p, objects, seed, avoid_xy):
        env = perturber.env
        low, high, z = distractor_region(env)
        m = MAGNITUDES["distractors"]
        g = rng(seed, p)
        xy = place_distractors(g, low, high, np.asarray(avoid_xy, float).reshape(-1, 2), len(objects), m["clearance_m"],
                               m["spacing_m"])
        placed = []
        for obj, (x, y) in zip(objects, xy):
            yaw = g.uniform(-np.pi, np.pi)
            quat = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
            height = z - float(obj.bottom_offset[2]) + 0.002
            env.sim.data.set_joint_qpos(obj.joints[0], np.concatenate([[x, y, height], quat]))
            placed.append({"object": obj.name, "xy": [round(float(x), 6), round(float(y), 6)]})
        perturber.record["distractors"] = placed


class InitStateKind(Kind):
    """The robot's initial joints offset and the objects' placement ranges widened, before robosuite's reset."""

    name, visual = "init-state", False

    def setup(self, perturber, p):
        samplers = uniform_samplers(getattr(perturber.env, "placement_initializer", None))
        return (np.array(perturber.env.robots[0].init_qpos, float),
                [(s, tuple(s.x_range), tuple(s.y_range)) for s in samplers])

    def before_reset(self, perturber, p, state, seed):
        nominal, samplers = state
        g = rng(seed, p)
        m = MAGNITUDES["init-state"]
        offset = g.uniform(-1, 1, size=nominal.shape) * m["joint_rad"] * p.level
        perturber.env.robots[0].init_qpos = nominal + offset
        widen = m["placement_m"] * p.level
        for sampler, xr, yr in samplers:
            if xr[0] == xr[1] and yr[0] == yr[1]:  # a fixed marker (PickPlace's visual objects)
                continue
            sampler.x_range = (xr[0] - widen, xr[1] + widen)
            sampler.y_range = (yr[0] - widen, yr[1] + widen)
        perturber.record["init-state"] = {"joint_offset_rad": offset.round(6).tolist(), "placement_widened_m": widen}


class NoiseKind(Kind):
    """Sensor noise on what the policy sees (blur, Gaussian noise, JPEG), drawn per step and camera."""

    name, keyed = "noise", True

    def setup(self, perturber, p):
        return p is find(perturber.perturbations, "noise")[0]  # frames: the first noise entry is applied (as ever)

    def after_reset(self, perturber, p, state, seed, avoid_xy):
        m = MAGNITUDES["noise"]
        perturber.record[p.condition] = {"blur_sigma_px": m["blur_sigma_px"] * p.level,
                                         "gaussian_sigma": m["gaussian_sigma"] * p.level,
                                         "jpeg_quality": int(90 - m["jpeg_quality_drop"] * p.level)}

    def frames(self, p, applied, frames, seed, step):
        if not applied:
            return frames
        return {key: (noise_frame(frame, seed, p, step, key) if p.camera in (None, key) else frame)
                for key, frame in frames.items()}


class LanguageKind(Kind):
    """The instruction rewritten (`instruction_for`, read by the env at reset); nothing in the scene changes."""

    name, visual = "language", False

    def check(self, task, p, instruction_override):
        if instruction_override is not None:
            raise PerturbationError(f"--perturb {p.label}: paraphrases exist for the tasks' own instructions, not for "
                                    "--instruction; drop one of them")
        if not task.paraphrases:
            raise PerturbationError(f"--perturb {p.label}: task {task.name} has no paraphrase list; drop language")


# The kinds, in their canonical order (parsing sorts by it, and kinds act in it; seeds come from KIND_SEEDS).
KIND_TABLE: dict[str, Kind] = {kind.name: kind for kind in (
    CameraKind(), LightingKind(), TextureKind(), DistractorsKind(), InitStateKind(), NoiseKind(), LanguageKind())}
KINDS = tuple(KIND_TABLE)
KEYED_KINDS = tuple(name for name, kind in KIND_TABLE.items() if kind.keyed)
