"""Strict JSON reading for the tests: NaN, Infinity and -Infinity are refused (issue 13: every
JSON tlsjax writes must be strict JSON)."""

import json
import pathlib


def _refuse(token):
    raise ValueError(f"non-strict JSON token {token}")


def load_strict(path):
    """Parse a JSON file, refusing NaN and infinities."""
    return json.loads(pathlib.Path(path).read_text(encoding="utf-8"), parse_constant=_refuse)


def check_tree(root) -> int:
    """Parse every ``*.json`` under ``root`` strictly; returns how many were checked. Leftover
    temporary files of an atomic write (``.tlsjax-*``) are an error too. Files under a
    folder named ``not_written_by_tlsjax`` (deliberately broken inputs of a test) are skipped."""
    root = pathlib.Path(root)
    n = 0
    for path in sorted(root.rglob("*.json")):
        if path.is_file() and "not_written_by_tlsjax" not in path.parts:
            try:
                load_strict(path)
            except ValueError as err:
                raise AssertionError(f"{path} is not strict JSON: {err}") from None
            n += 1
    left = sorted(root.rglob(".tlsjax-*"))
    assert not left, f"temporary files of an interrupted write left behind: {left}"
    return n
