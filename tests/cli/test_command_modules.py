"""The CLI imports only the module of a command listed in ``_COMMAND_HOME``: that module must
be the one that registers the command, and the command must work started alone."""

from __future__ import annotations

import subprocess
import sys

import tofhil.cli as cli


def test_command_home_is_the_registering_module():
    cli._register_command_modules()
    homes = {}
    for info in cli.app.registered_commands:
        name = info.name or info.callback.__name__.replace("_", "-")
        homes[name] = info.callback.__module__
    for command, module in cli._COMMAND_HOME.items():
        assert homes[command] == module
        assert module in cli.COMMAND_MODULES


def test_ndt_alone_imports_no_other_command_module():
    code = ("import sys, tofhil.cli as c\n"
            "try:\n    c.main(['ndt', '--help'])\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
            "others = [m for m in c.COMMAND_MODULES if m in sys.modules and m != 'tofhil.cli.ndt']\n"
            "print('OTHERS', others, 'numba' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "OTHERS [] False" in out
