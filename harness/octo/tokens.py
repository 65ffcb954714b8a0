"""Token map: for every key of the transformer sequence, its group, timestep and image patch.

This is the contract between the Octo runtime (which builds the sequence) and the attention
analysis (which turns a row of attention over keys into 2-D maps per camera). It is plain numpy
data so it can be saved next to attention arrays (`to_arrays` / `from_arrays`).

Group names follow Octo: `task_language` (prefix, timestep -1), then per timestep the observation
groups `obs_<tokenizer>` (image groups e.g. `obs_primary`, `obs_wrist`; low-dimensional groups e.g.
`obs_proprio`, one token per dimension), the repeated task group `obs_task_language`, and the
readouts `readout_<name>`. Any subset of these may be present (one camera, no language, proprio, ...).
Image tokens inside a group are row-major over the stem's output grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class TokenMap:
    group: np.ndarray  # (keys,) str: group name of each key
    timestep: np.ndarray  # (keys,) int32: window index, -1 for prefix (task) tokens
    row: np.ndarray  # (keys,) int32: patch row for image groups, -1 otherwise
    col: np.ndarray  # (keys,) int32: patch column for image groups, -1 otherwise
    image_groups: tuple[tuple[str, str, int, int], ...]  # (group, observation key, rows, cols)
    readout_index: np.ndarray  # (readouts,) int32: key positions of the last timestep's readouts

    @property
    def num_keys(self) -> int:
        return int(self.group.shape[0])

    @property
    def window(self) -> int:
        return int(self.timestep.max()) + 1

    def indices(self, group: str, timestep: int | None = None) -> np.ndarray:
        """(n,) key positions of `group` (optionally only at `timestep`), in sequence order."""
        sel = self.group == group
        if timestep is not None:
            sel &= self.timestep == timestep
        return np.flatnonzero(sel)

    def grid(self, group: str) -> tuple[int, int]:
        """(rows, cols) of the patch grid of an image group."""
        for name, _, rows, cols in self.image_groups:
            if name == group:
                return rows, cols
        raise KeyError(f"{group!r} is not an image group; image groups: {[g[0] for g in self.image_groups]}")

    def camera_group(self, observation_key: str) -> str:
        """Image group fed by an observation key, e.g. 'image_primary' -> 'obs_primary'."""
        for name, key, _, _ in self.image_groups:
            if key == observation_key:
                return name
        raise KeyError(f"no image group reads {observation_key!r}")

    def with_rows_flipped(self, observation_keys) -> "TokenMap":
        """The same map with the patch rows of the cameras fed by `observation_keys` reversed (row r -> rows-1-r).

        For models that see frames upside down (image convention "opengl"): their patch row r covers
        upright row rows-1-r, so with this map `camera_maps` & co. return maps in the upright frame.
        """
        keys = set(observation_keys)
        row = self.row.copy()
        for name, key, rows, _ in self.image_groups:
            if key in keys:
                sel = self.group == name
                row[sel] = rows - 1 - row[sel]
        row.flags.writeable = False
        return TokenMap(self.group, self.timestep, row, self.col, self.image_groups, self.readout_index)

    def with_cols_flipped(self, observation_keys) -> "TokenMap":
        """The same map with the patch columns of the cameras fed by `observation_keys` reversed (col c -> cols-1-c).

        For models that see frames mirrored left to right (image convention "rot180", LIBERO finetunes).
        """
        keys = set(observation_keys)
        col = self.col.copy()
        for name, key, _, cols in self.image_groups:
            if key in keys:
                sel = self.group == name
                col[sel] = cols - 1 - col[sel]
        col.flags.writeable = False
        return TokenMap(self.group, self.timestep, self.row, col, self.image_groups, self.readout_index)

    def to_arrays(self, prefix: str = "tokens/") -> dict[str, np.ndarray]:
        """Flat dict of arrays suitable for np.savez (no pickled objects)."""
        return {
            prefix + "group": self.group.astype("U32"),
            prefix + "timestep": self.timestep.astype(np.int32),
            prefix + "row": self.row.astype(np.int32),
            prefix + "col": self.col.astype(np.int32),
            prefix + "image_groups": np.array([g[0] for g in self.image_groups], dtype="U32"),
            prefix + "image_keys": np.array([g[1] for g in self.image_groups], dtype="U32"),
            prefix + "image_grids": np.array([[g[2], g[3]] for g in self.image_groups], dtype=np.int32).reshape(-1, 2),
            prefix + "readout_index": self.readout_index.astype(np.int32),
        }

    @classmethod
    def from_arrays(cls, arrays, prefix: str = "tokens/") -> "TokenMap":
        grids = np.asarray(arrays[prefix + "image_grids"]).reshape(-1, 2)
        return cls(
            group=np.asarray(arrays[prefix + "group"]).astype(str),
            timestep=np.asarray(arrays[prefix + "timestep"], dtype=np.int32),
            row=np.asarray(arrays[prefix + "row"], dtype=np.int32),
            col=np.asarray(arrays[prefix + "col"], dtype=np.int32),
            image_groups=tuple(
                (str(g), str(k), int(r), int(c))
                for g, k, (r, c) in zip(arrays[prefix + "image_groups"], arrays[prefix + "image_keys"], grids)
            ),
            readout_index=np.asarray(arrays[prefix + "readout_index"], dtype=np.int32),
        )


def build_token_map(
    prefix_groups: list[tuple[str, int]],
    timestep_groups: list[tuple[str, int]],
    window: int,
    image_groups: tuple[tuple[str, str, int, int], ...],
) -> TokenMap:
    """Lay out Octo's sequence: prefix groups, then for each timestep the timestep groups in order.

    prefix_groups / timestep_groups: [(group name, number of tokens)] in sequence order; image
    groups among them get row/col from `image_groups` (group, observation key, rows, cols).
    """
    grids = {g: (r, c) for g, _, r, c in image_groups}
    group, timestep, row, col = [], [], [], []

    def add(name: str, n: int, t: int) -> None:
        group.extend([name] * n)
        timestep.extend([t] * n)
        if name in grids:
            rows, cols = grids[name]
            assert rows * cols == n, (name, rows, cols, n)
            r, c = np.divmod(np.arange(n), cols)
            row.extend(r.tolist())
            col.extend(c.tolist())
        else:
            row.extend([-1] * n)
            col.extend([-1] * n)

    for name, n in prefix_groups:
        add(name, n, -1)
    for t in range(window):
        for name, n in timestep_groups:
            add(name, n, t)
    group_arr = np.array(group, dtype="U32")
    timestep_arr = np.array(timestep, dtype=np.int32)
    readout = np.flatnonzero(np.char.startswith(group_arr, "readout_") & (timestep_arr == window - 1))
    return TokenMap(
        group=group_arr,
        timestep=timestep_arr,
        row=np.array(row, dtype=np.int32),
        col=np.array(col, dtype=np.int32),
        image_groups=tuple(image_groups),
        readout_index=readout.astype(np.int32),
    )
