"""The rule both sides of the LIBERO pipe apply to the scene's names (pure Python, no imports).

Imported by the driver (`envs.libero_env`) and by the server (`envs/libero_server.py`, as a sibling module in LIBERO's
own environment), so it imports nothing.
"""

from __future__ import annotations


def owner(name: str, instances: list) -> str:
    """An object of interest -> the scene instance that holds it: itself, or the longest instance name it starts
    with (a BDDL region such as "wooden_cabinet_1_top_side" belongs to "wooden_cabinet_1"); ValueError (one line)
    when it belongs to none."""
    if name in instances:
        return name
    owners = [i for i in instances if name.startswith(i + "_")]
    if not owners:
        raise ValueError(f"object of interest {name!r} belongs to no scene object ({', '.join(instances)})")
    return max(owners, key=len)
