"""Video files of a rollout: an MP4 streamed through ffmpeg (imageio-ffmpeg's binary), and an optional small GIF.

Both write to a temporary name in the target directory (`<name>.tmp.mp4`, `<name>.tmp.gif`) and move
it into place with os.replace on `close()`, so a finished file is always complete; `abort()` deletes
the temporary file. Frames are (height, width, 3) uint8 of constant size.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from harness.files import temp_path


def _check_frame(frame: np.ndarray) -> np.ndarray:
    frame = np.asarray(frame)
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise ValueError(f"video frames must be (height, width, 3) uint8; got {frame.shape} {frame.dtype}")
    return frame


def pad_to_multiple(frame: np.ndarray, multiple: int) -> np.ndarray:
    """(h, w, 3) -> (h', w', 3) padded with black at the bottom / right to multiples of `multiple`."""
    h, w = frame.shape[:2]
    ph, pw = -h % multiple, -w % multiple
    if ph == 0 and pw == 0:
        return frame
    return np.pad(frame, ((0, ph), (0, pw), (0, 0)))


class Mp4Writer:
    """Streams frames to `path` (H.264, yuv420p) through the ffmpeg binary that imageio-ffmpeg ships.

    ffmpeg is started here with `start_new_session` rather than through imageio's writer, which
    starts it with a Python `preexec_fn`: forking with a preexec_fn from a multithreaded process
    (JAX runs threads) can hang and makes JAX warn. The new session also keeps Ctrl-C away from
    ffmpeg, so the caller decides between close() and abort().
    Frames are padded (not resampled) to multiples of 16. `close()` finishes the file and moves it
    into place, returning its path (None when no frame was written); `abort()` discards it.
    """

    MACRO_BLOCK = 16

    def __init__(self, path: str | os.PathLike, fps: float = 10, crf: int = 20, preset: str = "veryfast"):
        self.path = Path(path)
        if self.path.suffix != ".mp4":
            raise ValueError(f"MP4 path must end in .mp4: {self.path}")
        if fps <= 0:
            raise ValueError(f"fps must be positive; got {fps}")
        self.fps = fps
        self.crf = crf  # x264 constant quality: lower is better, 18-23 is visually good
        self.preset = preset  # x264 speed/size trade-off; veryfast costs a few ms per frame at 784x528
        self.temp = temp_path(self.path)
        self.frames = 0
        self._size: tuple[int, int] | None = None
        self._proc: subprocess.Popen | None = None
        self._log = None

    def _start(self, height: int, width: int) -> None:
        import imageio_ffmpeg

        self.path.parent.mkdir(parents=True, exist_ok=True)
        command = [
            imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error",
            "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{width}x{height}", "-r", f"{self.fps}", "-i", "-",
            "-an", "-c:v", "libx264", "-preset", self.preset, "-crf", str(self.crf), "-pix_fmt", "yuv420p",
            "-f", "mp4", str(self.temp),
        ]  # fmt: skip
        self._log = tempfile.TemporaryFile()
        self._proc = subprocess.Popen(
            command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=self._log, start_new_session=True
        )

    def _ffmpeg_error(self, what: str) -> RuntimeError:
        self._log.seek(0)
        message = self._log.read().decode(errors="replace").strip().splitlines()
        return RuntimeError(f"ffmpeg {what} for {self.path}: {message[-1] if message else 'no message'}")

    def append(self, frame: np.ndarray) -> None:
        """Encode one (height, width, 3) uint8 frame; every frame must have the first frame's size."""
        frame = _check_frame(frame)
        if self._size is None:
            self._size = frame.shape[:2]
            padded = pad_to_multiple(frame, self.MACRO_BLOCK)
            self._start(*padded.shape[:2])
        elif frame.shape[:2] != self._size:
            raise ValueError(f"video frame size changed from {self._size} to {frame.shape[:2]}; keep frames one size")
        if self._proc is None:
            raise RuntimeError(f"MP4 writer for {self.path} is closed")
        try:
            self._proc.stdin.write(np.ascontiguousarray(pad_to_multiple(frame, self.MACRO_BLOCK)).tobytes())
        except BrokenPipeError:
            self._proc.wait()
            raise self._ffmpeg_error("stopped") from None
        self.frames += 1

    def close(self) -> Path | None:
        proc, self._proc = self._proc, None
        if proc is None:
            return None
        try:
            proc.stdin.close()
        except BrokenPipeError:  # ffmpeg already gone; its exit code tells why
            pass
        try:
            if proc.wait() != 0:
                self.temp.unlink(missing_ok=True)
                raise self._ffmpeg_error(f"exited with code {proc.returncode}")
        finally:
            self._log.close()
        os.replace(self.temp, self.path)
        return self.path

    def abort(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            proc.kill()
            proc.wait()
            if proc.stdin:
                try:
                    proc.stdin.close()
                except OSError:  # broken pipe: ffmpeg is gone, as intended
                    pass
        if self._log is not None:
            self._log.close()
        self.temp.unlink(missing_ok=True)

    def __enter__(self) -> "Mp4Writer":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class GifWriter:
    """Keeps every `every`-th frame, shrunk by an integer `shrink` factor, and writes a looping GIF on close.

    Frames are held in memory until `close()` (GIF encoders need all frames), which is why they are
    thinned and shrunk; the GIF plays at fps / every frames per second so it lasts as long as the MP4.
    """

    def __init__(self, path: str | os.PathLike, fps: float = 10, every: int = 2, shrink: int = 2):
        self.path = Path(path)
        if self.path.suffix != ".gif":
            raise ValueError(f"GIF path must end in .gif: {self.path}")
        if every < 1 or shrink < 1 or fps <= 0:
            raise ValueError(f"GIF needs every >= 1, shrink >= 1, fps > 0; got every={every}, shrink={shrink}, fps={fps}")
        self.fps, self.every, self.shrink = fps, every, shrink
        self.temp = temp_path(self.path)
        self.seen = 0
        self._frames: list[np.ndarray] = []

    @property
    def frames(self) -> int:
        return len(self._frames)

    def append(self, frame: np.ndarray) -> None:
        frame = _check_frame(frame)
        if self.seen % self.every == 0:
            self._frames.append(np.ascontiguousarray(frame[:: self.shrink, :: self.shrink]))
        self.seen += 1

    def close(self) -> Path | None:
        if not self._frames:
            return None
        import imageio.v3 as iio

        frames, self._frames = self._frames, []
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            iio.imwrite(self.temp, np.stack(frames), extension=".gif", duration=1000.0 * self.every / self.fps, loop=0)
            os.replace(self.temp, self.path)
        except BaseException:
            self.temp.unlink(missing_ok=True)
            raise
        return self.path

    def abort(self) -> None:
        self._frames = []
        self.temp.unlink(missing_ok=True)
