"""benchmarks/register_scene.py: one scene timed, one JSON record."""

import json
import sys

import numpy as np
from conftest import ROOT, exact_result, scan_set, write_3dmatch_scene

sys.path.insert(0, str(ROOT / "benchmarks"))
import register_scene  # noqa: E402


class _Truth:
    """Registers every pair of a written scene by its truth (each fragment known by its first point)."""

    def __init__(self, clouds, poses):
        self.clouds, self.poses = clouds, poses

    def prepare_scans(self, clouds):
        return scan_set(clouds)

    def register_scan_pairs(self, scans, pairs, batch_size=8, on_pair=None):
        clouds = scans.clouds
        index = lambda cloud: int(np.argmin([np.abs(c[0] - cloud[0]).sum() for c in self.clouds]))  # noqa: E731
        motions = [np.linalg.inv(self.poses[index(clouds[t])]) @ self.poses[index(clouds[s])] for s, t in pairs]
        return [exact_result(m, "trusted") for m in motions]


def test_a_scene_is_timed_and_recorded(tmp_path, monkeypatch, capsys):
    from dit_jax import io
    from dit_jax.pipeline import registration

    rng = np.random.default_rng(0)
    poses = write_3dmatch_scene(tmp_path / "room", rng.normal(size=(200, 3)), rng, fragments=(0, 1, 2))
    clouds = [io.read(tmp_path / "room" / f"cloud_bin_{k}.ply") for k in range(3)]
    monkeypatch.setattr(registration, "load", lambda: _Truth(clouds, np.stack([poses[k] for k in range(3)])))
    assert register_scene.main(["--scenes", str(tmp_path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("room: 3 fragments, 3 pairs")
    record = json.loads(out[-1])
    (row,) = record["scenes"]
    assert record["benchmark"] == "register_scene" and row["groups"] == [3] and row["seconds_per_fragment"] >= 0
