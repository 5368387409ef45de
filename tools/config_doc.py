"""Rewrite the generated reference block of docs/CONFIG.md from the config schema.

    python3 tools/config_doc.py          # rewrite in place
    python3 tools/config_doc.py --check  # exit 1 if the file is stale

(The same text: ``dob-hil config --doc``. tests/test_config.py fails while the file is stale.)
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from dob_hil.config_doc import BEGIN, END, render_reference  # noqa: E402

DOC = ROOT / "docs" / "CONFIG.md"


def main(argv: list[str]) -> int:
    text = DOC.read_text(encoding="utf-8")
    start, end = text.index(BEGIN), text.index(END) + len(END) + 1
    new = text[:start] + render_reference() + text[end:]
    if "--check" in argv:
        if new != text:
            print(f"{DOC} is stale: run python3 tools/config_doc.py", file=sys.stderr)
            return 1
        return 0
    DOC.write_text(new, encoding="utf-8")
    print(f"{DOC}: reference block rewritten")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
