"""The one task resolver (envs.resolver): robosuite and LIBERO names, suites, 'all', one-line errors; the run
settings and `envs.get_task` go through it."""

import pytest

import envs
from envs import resolver
from envs.taskspec import TaskSpec, UnknownTaskError


def test_names_resolve_over_both_registries():
    assert resolver.resolve_names(["lift", "libero_goal/3", "Lift", "LIBERO_GOAL/3"]) == ("Lift", "libero_goal/3")
    assert resolver.resolve_names(["libero_spatial"]) == tuple(f"libero_spatial/{i}" for i in range(10))
    everything = resolver.resolve_names(["ALL"])
    assert everything[0] == "Lift" and len(everything) == len(envs.list_tasks())
    assert not any("/" in name for name in everything)  # 'all' = the robosuite tasks
    spec = resolver.get_task("libero_object/2")
    assert isinstance(spec, TaskSpec) and spec.simulator == "libero" and spec.max_episode_steps == 280
    assert resolver.get_task("stack") is resolver.get_task("Stack")


def test_unknown_names_are_one_line_naming_the_closest():
    with pytest.raises(UnknownTaskError, match="did you mean 'Stack'") as error:
        resolver.resolve_names(["Lift", "Stak"])
    assert "\n" not in str(error.value)
    with pytest.raises(UnknownTaskError, match="is a LIBERO suite"):
        resolver.get_task("libero_10")
    with pytest.raises(UnknownTaskError, match="libero_10/0 to libero_10/9"):
        resolver.resolve_names(["libero_10/10"])


def test_settings_and_the_package_use_the_one_resolver():
    from harness.run.settings import resolve_tasks

    assert envs.get_task is resolver.get_task and envs.UnknownTaskError is UnknownTaskError
    assert resolve_tasks(["lift,libero_goal/3", "Lift"]) == resolver.resolve_names(["lift", "libero_goal/3", "Lift"])


def test_robosuite_names_every_robosuite_task_and_all_stays_its_older_name():
    """`--task robosuite` runs what it says (issue 71 item 5.2); `all`, which ran the same, still does, and either
    joins a LIBERO suite in one list."""
    robosuite = tuple(spec.name for spec in envs.list_tasks())
    assert resolver.resolve_names(["robosuite"]) == resolver.resolve_names(["All"]) == robosuite
    assert resolver.resolve_names(["robosuite", "libero_goal/3", "Lift"]) == (*robosuite, "libero_goal/3")
    with pytest.raises(UnknownTaskError, match="`robosuite`: all of them"):
        resolver.resolve_names(["robosuit"])
