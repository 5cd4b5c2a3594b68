"""Pages a user can turn (:mod:`dit_jax.pictures.view`): self-contained, thinned, rendered by a browser."""

import numpy as np
import pytest
from conftest import rendered_legend

from dit_jax.pictures import view


def test_a_page_renders_one_trace_per_cloud_and_holds_at_most_its_points(tmp_path):
    rng = np.random.default_rng(0)
    clouds = [rng.normal(size=(3000, 3)), rng.normal(size=(1000, 3)) + 3.0]
    html = view.page(clouds, ["big.ply", "small.ply"], title="two clouds", max_points=400,
                     lines=[view.Lines("a segment", np.array([[[0, 0, 0], [3, 3, 3]]]))])  # fmt: skip
    import re

    assert "<script" in html and not re.search(r"<script[^>]*src=", html), "the page carries its script: offline"
    path = view.write(tmp_path / "page.html", html)
    assert rendered_legend(path) == ["big.ply", "small.ply", "a segment"]
    # 400 points in all, in proportion: 300 and 100 (each shown as x, y and z arrays in the page's data).
    import json

    data = json.loads(re.search(r"Plotly\.newPlot\(\s*\"[^\"]+\",\s*(\[.*?\]),\s*\{", html, re.S).group(1))
    import base64

    def count(values) -> int:  # plotly writes arrays as lists or as base64 typed arrays
        if isinstance(values, dict):
            return len(base64.b64decode(values["bdata"])) // np.dtype(values["dtype"]).itemsize
        return len(values)

    assert [count(trace["x"]) for trace in data[:2]] == [300, 100]
    with pytest.raises(ValueError, match="2 clouds for 1 names"):
        view.page(clouds, ["one"], title="")


def test_a_pair_result_writes_a_page_of_target_source_and_the_source_moved(tmp_path):
    from dit_jax.pipeline import result as result_lib

    motion = np.eye(4)
    motion[:3, 3] = [1.0, 0.0, 0.0]
    found = result_lib.Result(motion[:3, :3], motion[:3, 3], motion, np.arange(3), np.arange(3), np.ones(3), 1.0,
                              1.0, 0.0, refinement="icp", refine_seconds=0.0, verdict=True, level="trusted",
                              verdict_rule="agreement", threshold=1.0, agreement=0.1, direction="forward",
                              start_turn=0.0, agreement_band=None)  # fmt: skip
    cloud = np.random.default_rng(1).normal(size=(200, 3))
    path = found.plot(tmp_path / "pair.html", cloud, cloud + [1.0, 0.0, 0.0])
    assert rendered_legend(path) == ["target", "source", "source moved"]
