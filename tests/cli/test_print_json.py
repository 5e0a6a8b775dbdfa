"""``tofhil.cli.print_json``: into a pipe it writes, without rich, the text rich wrote."""

from __future__ import annotations

import io
import json

import pytest
from rich.console import Console

from tofhil.cli import print_json


@pytest.mark.parametrize("data", [
    {"score_per_point": 0.1 + 0.2, "cells": 62, "nan": float("nan"), "inf": float("-inf"), "x": None},
    {"path": "/a/very/long/" + "directory/" * 20 + "file with spaces and ünïcode ✓.pcd", "list": [1, 2.5, [3, {}]]},
    [{"spec": "emulator:bench_demo", "kind": "raw", "description": "[bold]not markup[/bold] \x1b"}],
    [],
])
def test_json_into_a_pipe_is_what_rich_printed(data, capsys):
    buf = io.StringIO()
    Console(file=buf, emoji=False, width=80).print_json(json.dumps(data))
    print_json(data)
    assert capsys.readouterr().out == buf.getvalue()
