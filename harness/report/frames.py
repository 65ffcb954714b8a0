"""Frames the report reads back from what a run recorded, decoding only the ones it shows:

- `read_video_frames`: chosen frames of an episode's rollout.mp4, cropped to its top-left corner (one ffmpeg pass
  with a select filter; the overlay grids of harness.report.build and the Failures section read it);
- `npz_row`: one step of one array of an episode's .npz (a camera frame of inputs.npz, a step of attention.npz's
  readout attention), read from the zip member's stream without loading the other steps; its headers are checked
  first (harness.bounded), as every reader of a run folder does.
"""

from __future__ import annotations

import logging
import zipfile
from pathlib import Path

import numpy as np

from harness.bounded import check_npz

VIDEO_DISPLAY = 256  # harness.outputs.overlays.video_frame's `display`: the camera frame fills the video's top-left display x w


def _drop_crop_note(record: logging.LogRecord) -> bool:
    """imageio-ffmpeg warns that a cropped read differs from the video's size: intended here."""
    return "different from the source frame size" not in record.getMessage()


def read_video_frames(path: Path, indices: list[int], height: int, width: int) -> dict[int, np.ndarray]:
    """Frames `indices` of an MP4, cropped to the top-left height x width -> {index: (height, width, 3) uint8}.

    One ffmpeg pass with a select filter (only the chosen frames are converted); {} when the video is unreadable.
    """
    import imageio_ffmpeg

    if not indices:
        return {}
    select = "+".join(f"eq(n\\,{i})" for i in sorted(set(indices)))
    logging.getLogger("imageio_ffmpeg").addFilter(_drop_crop_note)  # once (a filter is added only once)
    try:
        reader = imageio_ffmpeg.read_frames(str(path), input_params=["-skip_loop_filter", "all"], output_params=[
            "-vf", f"select={select},crop={width}:{height}:0:0", "-fps_mode", "passthrough"])  # thumbnails: no deblocking
        meta = next(reader)
        if meta["source_size"][0] < width or meta["source_size"][1] < height:
            reader.close()
            return {}
        frames = [np.frombuffer(buf, np.uint8).reshape(height, width, 3).copy() for buf in reader]
    except (OSError, RuntimeError, StopIteration, ValueError):
        return {}
    return dict(zip(sorted(set(indices)), frames))


def npz_row(path: Path, name: str, index: int, steps: int | None = None) -> np.ndarray | None:
    """Row `index` of member `name` of a .npz (e.g. input/image_primary of inputs.npz: one (H, W, 3) frame), None
    when the member or the row is absent. Only that row is kept: a compressed member is decompressed as a stream up
    to it, never whole. The archive's headers are checked against `steps` first (BoundsError, a ValueError)."""
    from numpy.lib import format as npformat

    headers = check_npz(path, steps)
    if name not in headers:
        return None
    shape, dtype = headers[name]
    if not shape or not 0 <= index < shape[0]:
        return None
    row_shape = tuple(shape[1:])
    size = int(np.prod(row_shape, dtype=np.int64)) * dtype.itemsize
    with zipfile.ZipFile(path) as archive, archive.open(name + ".npy") as member:
        version = npformat.read_magic(member)
        header = npformat.read_array_header_1_0 if version == (1, 0) else npformat.read_array_header_2_0
        _, fortran, _ = header(member, max_header_size=10_000)
        if fortran and len(row_shape) > 0:  # a row is not contiguous: read the member (not what the writers make)
            with np.load(path, allow_pickle=False) as z:
                return np.array(z[name][index])
        member.seek(member.tell() + index * size)  # a compressed member: decompressed in chunks up to the row
        data = member.read(size)
    if len(data) != size:
        return None
    return np.frombuffer(data, dtype).reshape(row_shape).copy()
