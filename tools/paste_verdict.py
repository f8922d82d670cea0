"""Pastes a generated verdict (docs/study/verdict.md) into the README between its markers.

    python3 tools/paste_verdict.py docs/study/verdict.md README.md

The README holds the block between `<!-- STUDY-VERDICT ... -->` and `<!-- /STUDY-VERDICT -->`;
everything between them is replaced, its headings moved down to level 4 (the block sits inside
a level-3 section). Written atomically (temp file + rename); fails, writing nothing, when the
markers are missing or out of order.
"""

import os
import re
import sys
import tempfile

BEGIN = "<!-- STUDY-VERDICT: generated, do not edit by hand: docs/study/verdict.md -->"
END = "<!-- /STUDY-VERDICT -->"


def paste(readme: str, verdict: str) -> str:
    start, stop = readme.find(BEGIN), readme.find(END)
    if start < 0 or stop < start:
        raise ValueError(f"README: markers {BEGIN!r} ... {END!r} missing or out of order")
    body = re.sub(r"^#{1,4} ", "#### ", verdict.strip(), flags=re.M)
    return readme[: start + len(BEGIN)] + "\n\n" + body + "\n\n" + readme[stop:]


def main(verdict_path: str, readme_path: str) -> None:
    with open(verdict_path, encoding="utf-8") as f:
        verdict = f.read()
    with open(readme_path, encoding="utf-8") as f:
        readme = f.read()
    try:
        text = paste(readme, verdict)
    except ValueError as e:
        sys.exit(f"{readme_path}: {e}")
    folder = os.path.dirname(os.path.abspath(readme_path))
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".readme-")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    os.chmod(tmp, os.stat(readme_path).st_mode & 0o777)
    os.replace(tmp, readme_path)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: paste_verdict.py VERDICT.md README.md")
    main(sys.argv[1], sys.argv[2])
