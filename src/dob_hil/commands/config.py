"""``dob-hil config --doc | --template [--out FILE]`` and ``dob-hil init FILE``.

``--doc``: the reference of every config key (type, unit, default, range, meaning), rendered from
the schema the parser uses (the same text as ``docs/CONFIG.md``'s reference part).
``--template`` / ``init``: a commented starter config (the paper's motor, every key listed) that
parses, designs and runs as written. A file is never overwritten.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dob_hil.errors import ConfigError


def write_new_file(path: Path, text: str, option: str) -> None:
    """Write ``text`` to ``path``, which must not exist yet."""
    from dob_hil.commands.paths import ensure_file_parent

    ensure_file_parent(path, option)
    try:
        with path.open("x", encoding="utf-8") as f:
            f.write(text)
    except FileExistsError:
        raise ConfigError(option, f"{path} exists; not overwritten") from None
    except OSError as exc:
        raise ConfigError(option, f"cannot write {path}: {exc.strerror or type(exc).__name__}") from None


def main(args: argparse.Namespace) -> int:
    from dob_hil.config_doc import render_reference, render_template

    if args.command == "init":
        write_new_file(Path(args.path), render_template(), "path")
        print(f"{args.path}: a commented starter config; check it with `dob-hil design {args.path}`")
        return 0
    text = render_reference() if args.doc else render_template()
    if args.out:
        write_new_file(Path(args.out), text, "--out")
    else:
        print(text, end="")
    return 0
