"""The shipped Foxglove layout: current, and plotting only fields the log (and the live view) has."""

from __future__ import annotations

import json
import re
from importlib import resources

import pytest

pytest.importorskip("foxglove", reason="the live extra (foxglove-sdk) is not installed")

from dob_hil.live.layout import LAYOUT_PATH, LIMITS_TOPIC, layout_text, plotted_paths
from dob_hil.log.schemas import TOPIC_EVENT, LogLayout, channel_specs

PATH = re.compile(r"^(?P<topic>/[\w/]+)\.(?P<field>\w+)(\[(?P<index>\d+)\])?$")


def test_the_shipped_layout_is_the_generated_one() -> None:
    assert LAYOUT_PATH.read_text() == layout_text(), "run: python -m dob_hil.live.layout"


def test_the_layout_is_package_data() -> None:
    text = resources.files("dob_hil.live").joinpath("layout.json").read_text()
    assert json.loads(text)["version"] == 1


def test_every_plotted_path_names_a_field_of_the_logs_schemas() -> None:
    layout = LogLayout(n_states=4, n_inputs=1, n_outputs=1, n_plant_states=2)  # the paper's plant
    fields = {s.topic: {f.name: f for f in s.fields or ()} for s in channel_specs(layout)}
    paths = [p for series in plotted_paths().values() for p, _label in series]
    assert len(plotted_paths()) == 4  # position/reference, disturbance/estimate, command/limits, timing
    for path in paths:
        m = PATH.match(path)
        assert m is not None, path
        if m["topic"] == LIMITS_TOPIC:
            assert m["field"] in ("upper_a", "lower_a")
            continue
        field = fields[m["topic"]][m["field"]]
        if m["index"] is not None:
            assert field.count is not None and int(m["index"]) < field.count, path
    text = LAYOUT_PATH.read_text()
    assert all(path in text for path in paths)
    assert TOPIC_EVENT in text and LIMITS_TOPIC in text
