"""The shipped Foxglove layout (``layout.json`` beside this module), built with ``foxglove.layouts``.

The paper's plots, on the log's own topics and fields, so the one layout serves the live view
(``dob-hil run --live``) and a logged run opened from its MCAP file: position and reference,
the disturbance and its estimate, the command and its limits, timing, and the events. The
current limit is a layout variable (``current_limit_A``, the paper scenarios' 0.7 A), drawn by a
small user script, since a plot cannot draw a constant. Regenerate with
``python -m dob_hil.live.layout`` (a test checks the shipped file is current).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from dob_hil.log.schemas import TOPIC_EVENT, TOPIC_SAMPLE, TOPIC_TRUTH

LAYOUT_PATH = Path(__file__).with_name("layout.json")
LIMITS_TOPIC = "/foxglove_script/dob_hil_current_limits"  # the user script's output (not in the log)
DEFAULT_CURRENT_LIMIT_A = 0.7

LIMITS_SCRIPT = f"""\
// The configured current limit (the layout variable current_limit_A) beside each sample,
// so the command plot can draw it. Set the variable to the run's drive.current_limit_A.
import {{ Input }} from "./types";

export const inputs = ["{TOPIC_SAMPLE}"];
export const output = "{LIMITS_TOPIC}";

type Output = {{ upper_a: number; lower_a: number }};

export default function script(
  event: Input<"{TOPIC_SAMPLE}">,
  globalVars?: Record<string, unknown>,
): Output {{
  const limit = Number(globalVars?.current_limit_A ?? {DEFAULT_CURRENT_LIMIT_A});
  return {{ upper_a: limit, lower_a: -limit }};
}}
"""


def plotted_paths() -> dict[str, list[tuple[str, str]]]:
    """Plot title -> [(message path, label)]; the paths name the log's topics and fields."""
    s, t = TOPIC_SAMPLE, TOPIC_TRUTH
    return {
        "Position and reference": [
            (f"{s}.x_ref[0]", "reference r (x_ref[0])"),
            (f"{s}.position[0]", "measured y"),
            (f"{t}.state[0]", "true position (simulated drive)"),
        ],
        "Disturbance and its estimate (A)": [
            (f"{t}.disturbance_a[0]", "injected disturbance (simulated drive)"),
            (f"{s}.u_dist[0]", "DOB compensation u_dist"),
        ],
        "Command and limits (A)": [
            (f"{s}.u_cmd_a[0]", "commanded u_cmd"),
            (f"{s}.u_applied_a[0]", "sent (limited, quantized)"),
            (f"{LIMITS_TOPIC}.upper_a", "+limit"),
            (f"{LIMITS_TOPIC}.lower_a", "-limit"),
        ],
        "Timing (ns)": [
            (f"{s}.lateness_ns", "feedback lateness"),
            (f"{s}.compute_ns", "controller step"),
        ],
    }


def build_layout() -> Any:
    """The layout as a ``foxglove.layouts.Layout``."""
    import foxglove.layouts as fl

    def plot(title: str, series: list[tuple[str, str]]) -> Any:
        paths = [fl.PlotSeries(value=path, label=label, enabled=True) for path, label in series]
        return fl.PlotPanel(
            title=title,
            config=fl.PlotConfig(paths=paths, show_legend=True, legend_display="top", is_synced=True),
        )

    plots = [fl.SplitItem(content=plot(title, series)) for title, series in plotted_paths().items()]
    side = fl.SplitContainer(
        direction="column",
        items=[
            fl.SplitItem(proportion=2, content=fl.RawMessagesPanel(
                title="Events", config=fl.RawMessagesConfig(topic_path=TOPIC_EVENT))),
            fl.SplitItem(proportion=1, content=fl.ParametersPanel(title="Design and run (live)")),
        ],
    )  # fmt: skip
    return fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[
                fl.SplitItem(proportion=3, content=fl.SplitContainer(direction="column", items=plots)),
                fl.SplitItem(proportion=1, content=side),
            ],
        ),
        variables={"current_limit_A": DEFAULT_CURRENT_LIMIT_A},
        user_scripts={"current_limits": fl.UserScript(name="current limits", source_code=LIMITS_SCRIPT)},
    )


def layout_text() -> str:
    """The layout file's text (indented JSON, a final newline)."""
    return json.dumps(json.loads(build_layout().to_json()), indent=2) + "\n"


if __name__ == "__main__":
    LAYOUT_PATH.write_text(layout_text())
    print(f"wrote {LAYOUT_PATH}")
