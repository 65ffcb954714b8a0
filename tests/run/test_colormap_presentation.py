"""The overlays' colour map is presentation (issue 67 item 5): viridis by default, jet still selectable, recorded in
the manifest's "presentation" outside the protocol and its hash, so a run made when the colour map was part of the
protocol (its hash over `protocol.outputs.cmap`) still resumes, and draws its new episodes as it drew the old ones."""

from __future__ import annotations

import json
import shutil

import pytest

from harness import cli
from harness.outputs.writers import OutputOptions
from harness.run.protocol import Protocol
from harness.runfolder.schema import protocol_hash


def test_the_colour_map_is_outside_the_protocol_hash():
    viridis = Protocol(model="random:octo-small-1.5", tasks=("Lift",))
    jet = viridis.replace(outputs=OutputOptions(cmap="jet"))
    assert viridis.outputs.cmap == "viridis" and jet.outputs.cmap == "jet"
    assert "cmap" not in viridis.to_dict()["outputs"] and viridis.hash() == jet.hash()
    assert jet.outputs.presentation() == {"cmap": "jet"}
    with pytest.raises(ValueError, match="unknown colormap"):
        OutputOptions(cmap="no-such-map")


@pytest.mark.slow
def test_a_run_made_with_the_colour_map_in_its_protocol_still_resumes(fixtures_dir, tmp_path):
    command = ["run", "--task", "Lift", "--episodes", "2", "--model", str(fixtures_dir / "tiny"), "--max-steps", "2",
               "--png-every", "0", "--no-video", "--no-masks", "--fast-render", "--out", str(tmp_path)]
    assert cli.main([*command, "--run-name", "new", "--colormap", "inferno"]) == 0
    manifest = json.loads((tmp_path / "new" / "manifest.json").read_text())
    assert manifest["presentation"] == {"cmap": "inferno"} and "cmap" not in manifest["protocol"]["outputs"]
    episode = json.loads((tmp_path / "new" / "Lift" / "episode_1" / "episode.json").read_text())
    assert episode["options"]["cmap"] == "inferno"

    # as a run made before: jet inside the protocol and its hash, no "presentation"; its second episode unrecorded
    old = tmp_path / "old"
    shutil.copytree(tmp_path / "new", old)
    manifest.pop("presentation")
    manifest["protocol"]["outputs"]["cmap"] = "jet"
    manifest["protocol_hash"] = protocol_hash(manifest["protocol"])
    (old / "manifest.json").write_text(json.dumps(manifest))
    rows = (old / "results.jsonl").read_text().splitlines()
    (old / "results.jsonl").write_text(rows[0] + "\n")
    shutil.rmtree(old / "Lift" / "episode_1")

    assert cli.main(["run", "--resume", str(old)]) == 0
    after = json.loads((old / "manifest.json").read_text())
    assert after["protocol_hash"] == manifest["protocol_hash"] and after["protocol"] == manifest["protocol"]
    assert "presentation" not in after  # the record of the run is left as it was
    episode = json.loads((old / "Lift" / "episode_1" / "episode.json").read_text())
    assert episode["options"]["cmap"] == "jet"  # drawn as the run began
    assert len((old / "results.jsonl").read_text().splitlines()) == 2
    assert cli.main([*command, "--run-name", "old"]) == 0  # the same command finds nothing to change
