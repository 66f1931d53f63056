"""Regenerate the generated parts of docs/; run from the repository root.

    python docs/generate.py study [--doc DOC] [--out DIR] [masking-lab study options]
    python docs/generate.py efficiency [--no-psi]

``study`` runs ``masking-lab study --out docs/study`` (about 5 min on 2 cores) and pastes the
blocks it writes (docs/study/blocks/NAME.md) into the ``<!-- study:NAME -->`` …
``<!-- /study:NAME -->`` blocks of docs/speed-accuracy.md, leaving the rest of the document as
it is. ``efficiency`` prints the efficiency table of docs/procedures.md (about 2.5 min; the
psi-marginal is most of it). The package itself never writes into docs/: this script, outside
it, is the only thing that does. Exit 0, or 2 when the document cannot be read or lacks a block
(checked before the minutes of simulation).
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

_BLOCK = re.compile(
    r"(<!-- study:(?P<name>[a-z_]+) -->\n)(?P<body>.*?)(<!-- /study:(?P=name) -->)", re.S
)


class DocError(Exception):
    """The document cannot be read or lacks a generated block."""


def fill_doc(text: str, blocks: dict[str, str]) -> str:
    """Replace the body of each ``<!-- study:NAME -->`` block of ``text`` with ``blocks[NAME]``.

    Raises
    ------
    DocError
        If a block is missing from the document (naming it and the markers to add).

    Examples
    --------
    >>> fill_doc("a\\n<!-- study:x -->\\nold\\n<!-- /study:x -->\\n", {"x": "new"})
    'a\\n<!-- study:x -->\\nnew\\n<!-- /study:x -->\\n'
    """
    found = {m.group("name") for m in _BLOCK.finditer(text)}
    missing = sorted(set(blocks) - found)
    if missing:
        raise DocError(
            f"the study document has no generated block(s) {missing}; add "
            + ", ".join(f"'<!-- study:{n} -->' … '<!-- /study:{n} -->'" for n in missing)
        )

    def sub(m: re.Match[str]) -> str:
        name = m.group("name")
        if name not in blocks:
            return m.group(0)
        return f"{m.group(1)}{blocks[name].rstrip()}\n{m.group(4)}"

    return _BLOCK.sub(sub, text)


def _read(doc: Path) -> str:
    try:
        return doc.read_text(encoding="utf-8")
    except OSError as exc:
        raise DocError(f"{doc}: cannot read the study document ({exc.strerror})") from exc


def study(doc: Path, out: Path, study_args: list[str]) -> int:
    """Run ``masking-lab study --out OUT STUDY_ARGS`` and paste its blocks into ``doc``."""
    from masking_lab.commands.cli import main as cli_main
    from masking_lab.formats.fileio import write_text_atomic
    from masking_lab.planning.study import BLOCKS

    text = _read(doc)
    fill_doc(text, dict.fromkeys(BLOCKS, ""))  # fail before minutes of simulation
    code = cli_main(["study", "--out", str(out), *study_args])
    if code:
        return code
    blocks = {n: (out / "blocks" / f"{n}.md").read_text(encoding="utf-8") for n in BLOCKS}
    write_text_atomic(doc, fill_doc(text, blocks))
    print(f"wrote {out}/ and {doc}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Command line of this script; see the module docstring."""
    parser = argparse.ArgumentParser(prog="docs/generate.py", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    s = sub.add_parser("study", help="docs/study/ and the blocks of docs/speed-accuracy.md")
    s.add_argument("--doc", type=Path, default=Path("docs/speed-accuracy.md"))
    s.add_argument("--out", type=Path, default=Path("docs/study"))
    e = sub.add_parser("efficiency", help="print the efficiency table of docs/procedures.md")
    e.add_argument("--no-psi", action="store_true", help="skip the slow psi-marginal")
    args, rest = parser.parse_known_args(argv)
    try:
        if args.what == "study":
            return study(args.doc, args.out, rest)
        if rest:
            parser.error(f"unrecognized arguments: {' '.join(rest)}")
        from masking_lab.procedures.efficiency import report

        print(report(psi=not args.no_psi))
        return 0
    except DocError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
