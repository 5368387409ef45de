"""The config reference (Markdown) and a commented starter config (TOML), both rendered from
:data:`dob_hil.config_schema.SCHEMA`, the table the parser validates against.

``docs/CONFIG.md`` holds :func:`render_reference` between :data:`BEGIN` and :data:`END`; a test
fails when the two differ, and ``dob-hil config --doc`` prints the current text
(``python3 tools/config_doc.py`` rewrites the block in place).
"""

from __future__ import annotations

from dob_hil.config_schema import (
    MAX_AUGMENTED_STATES,
    MAX_DELAY_SAMPLES,
    MAX_INPUTS,
    MAX_MATRIX_ENTRY,
    MAX_OUTPUTS,
    MAX_STATES,
    MAX_TIME_S,
    REQUIRED,
    SCHEMA,
    Field,
    SectionSpec,
)

BEGIN = "<!-- BEGIN GENERATED REFERENCE (dob-hil config --doc) -->"
END = "<!-- END GENERATED REFERENCE -->"


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _default_text(f: Field) -> str:
    if f.default == REQUIRED:
        return "**required**"
    if f.default is None:
        return "not set"
    if isinstance(f.default, str) and f.kind != "string":
        return f.default  # described in words
    if f.kind == "string" and f.default == "the file name's stem":
        return str(f.default)
    if f.kind == "number" and isinstance(f.default, float) and f.default == 1.0 / 2048.0:
        return "0.00048828125 (1/2048)"
    return f"`{_toml_value(f.default)}`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _table_header(spec: SectionSpec) -> str:
    if spec.path.endswith("[]"):
        return f"[[{spec.path[:-2]}]]"
    return f"[{spec.path}]"


def render_reference() -> str:
    """Markdown: one table per section, every key with type, unit, default, range and meaning."""
    out = [
        BEGIN,
        "",
        "Types: *number* (integer or float), *integer*, *boolean*, *string*, *matrix* (a number, a "
        "flat list or a list of rows; a flat list is a column where a column is meant), *list of "
        "numbers/integers/strings*. Unknown keys are errors. Ranges are inclusive unless written "
        f"with < or >. Every matrix entry has a magnitude <= {MAX_MATRIX_ENTRY:g}; every time is "
        f"at most {MAX_TIME_S:g} s. Plant size: at most {MAX_STATES} states, {MAX_INPUTS} inputs, "
        f"{MAX_OUTPUTS} outputs, {MAX_DELAY_SAMPLES} delay samples and {MAX_AUGMENTED_STATES} "
        "augmented states (n + delay x m); n_aug below is that augmented state count.",
        "",
    ]
    for spec in SCHEMA:
        out += [f"### `{_table_header(spec)}`", "", spec.doc, ""]
        out += ["| key | type | unit | default | range | meaning |", "|---|---|---|---|---|---|"]
        for f in spec.fields:
            kind = (
                f"matrix {f.shape}"
                if f.kind == "matrix" and f.shape
                else f.kind.replace("numbers", "list of numbers")
                .replace("integers", "list of integers")
                .replace("strings", "list of strings")
            )
            out.append(
                f"| `{f.key}` | {kind} | {_cell(f.unit)} | {_cell(_default_text(f))} | "
                f"{_cell(f.range_text())} | {_cell(f.doc)} |"
            )
        out.append("")
    out += [_profile_section(), "", END]
    return "\n".join(out) + "\n"


def _profile_section() -> str:
    from dob_hil.profiles import all_profiles

    lines = ["### `[drive.<profile>]`", ""]
    lines.append(
        "A drive profile's own options, read by the profile (see `dob_hil.profiles`). Registered "
        "profiles: " + ", ".join(f"`{p.name}` ({p.summary})" for p in all_profiles()) + "."
    )
    return "\n".join(lines)


def render_template() -> str:
    """A commented starter config: the paper's motor, every section, every key as a comment or
    a value, so that it parses, designs and runs as written."""
    out = [
        "# dob_hil config: a starter. Every key is listed; commented keys show their default.",
        "# Reference: docs/CONFIG.md (or `dob-hil config --doc`). Check it: `dob-hil design THIS.toml`.",
        "# The values below are the paper's motor (Lee, Kim, Baek, ACC 2000): replace them with yours.",
    ]
    for spec in SCHEMA:
        header = _table_header(spec)
        if spec.path.endswith("[]") and not any(f.example or f.default == REQUIRED for f in spec.fields):
            header = f"# {header}"  # an optional array of tables whose keys are all commented
        out += ["", *(f"# {line}" for line in _wrap(spec.doc)), header]
        for f in spec.fields:
            unit = f" [{f.unit}]" if f.unit else ""
            rng = f" Range: {f.range_text()}." if f.range_text() else ""
            if f.example or f.default == REQUIRED:
                line = f"{f.key} = {f.example}"
            elif f.default is not None and not _is_words(f):
                line = f"# {f.key} = {_toml_value(f.default)}"
            else:
                line = f"# {f.key} =    (not set: {f.default or 'none'})"
            out.append(line)
            out += [f"    # {text}" for text in _wrap(f"{f.doc}{unit}{rng}", 92)]
    return "\n".join(_strip_blank_runs(out)) + "\n"


def _is_words(f: Field) -> bool:
    return isinstance(f.default, str) and (f.kind != "string" or f.default == "the file name's stem")


def _wrap(text: str, width: int = 98) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width) or [""]


def _strip_blank_runs(lines: list[str]) -> list[str]:
    out: list[str] = []
    for line in lines:
        if line == "" and out and out[-1] == "":
            continue
        out.append(line)
    return out
