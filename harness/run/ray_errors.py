"""What a Ray error says, in one line: the underlying message, why an actor died, and whether a worker or its node
was lost (harness.run.ray_executor records these for its episodes and its start-up)."""

from __future__ import annotations

import re
import time

NODE_DEATH_WAIT_S = 10.0  # how long a worker lost without an exit report waits for Ray to say whether its node died


def last_line(exc: BaseException) -> str:
    """The last non-empty line of a Ray error (the underlying exception's message)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    line = lines[-1] if lines else type(exc).__name__
    return line.split("RayExecutorError: ", 1)[-1]  # our own one-line errors, raised inside an actor


def actor_error(exc: BaseException) -> str:
    """A Ray actor error in one line: Ray's own reason (its error-message line: e.g. the node was marked dead, the
    owner died) and whether the actor ever ran, without Ray's generic first line and ids."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    kept = [line for line in lines[1:] if not re.match(r"(class_name|actor_id|pid|name|namespace|ip):", line)]
    return " ".join(kept)[:400] or last_line(exc)


def actor_death_cause(exc: BaseException, lost: str = "worker") -> str:
    """A Ray actor error -> the error recorded for its episode: where it ran and Ray's exit detail (or, where its
    node was `lost`, that)."""
    text = " ".join(str(exc).split())
    pid, ip = re.search(r"\bpid: (\d+)", text), re.search(r"\bip: (\S+)", text)
    detail = re.search(r"Worker exit detail: (.*)", text)
    where = f" (pid {pid.group(1)}{' on ' + ip.group(1) if ip else ''})" if pid else ""
    if lost == "node" or (detail is None and "its node has died" in text):
        return f"worker process died{where}: its node died"
    return f"worker process died{where}: {(detail.group(1) if detail else text)[:300]}"


def lost_part(exc: BaseException, node_alive=None) -> str:
    """What a Ray actor error says was lost: "node" when the actor's node died, else "worker". Where Ray's error
    says neither (no raylet reported the worker's exit: its node went with it), `node_alive()` (None: unknown, else
    whether the actor's node still lives) is asked until it answers, for NODE_DEATH_WAIT_S at most."""
    text = " ".join(str(exc).split())
    if re.search(r"node (has )?died|node .*(marked|is) dead|raylet .*died|node_death", text.lower()):
        return "node"
    if node_alive is None or "Worker exit detail" in text:
        return "worker"
    deadline = time.monotonic() + NODE_DEATH_WAIT_S
    while time.monotonic() < deadline:
        alive = node_alive()
        if alive is not None and not alive:
            return "node"
        time.sleep(0.25)
    return "worker"
