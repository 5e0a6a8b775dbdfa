"""The CLI's direct coercion (``tofhil.cli.coercion``) gives what typer's own gives: the same
values, the same one-line errors, and typer's coercion for the kinds it does not handle."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import pytest
import typer

from tofhil.cli import coercion
from tofhil.cli import options as opt


def _app(seen: dict) -> typer.Typer:
    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)

    @app.command()
    def run(name: str = typer.Argument(..., help="A name."),
            size: float = typer.Option(0.5, "--size", parser=opt.finite(0.0, 10.0, lo_open=True, unit="m")),
            count: int = typer.Option(3, "--count", parser=opt.count(1, 9)),
            sizes: Optional[List[float]] = typer.Option(None, "--sizes", parser=opt.finite(0.0, 1.0)),
            tags: Optional[List[str]] = typer.Option(None, "--tag"),
            where: Path = typer.Option(Path("."), "--where"),  # no parser: typer's own coercion
            loud: bool = typer.Option(False, "--loud", envvar="TOFHIL_TEST_LOUD")) -> None:
        seen.update(name=name, size=size, count=count, sizes=sizes, tags=tags, where=where, loud=loud)

    @app.command()
    def other(flag: bool = typer.Option(False, "--flag")) -> None:
        seen.update(flag=flag)

    return app


def _invoke(args: list[str], direct: bool, env: dict | None = None) -> tuple[object, dict]:
    """Exit code or the usage error's message, and the values the command received."""
    seen: dict = {}
    command = typer.main.get_command(_app(seen))
    if direct:
        assert coercion.install(command) > 0
    try:
        with pytest.MonkeyPatch.context() as mp:
            for k, v in (env or {}).items():
                mp.setenv(k, v)
            command.main(args, prog_name="t", standalone_mode=False)
        result: object = 0
    except Exception as exc:  # a usage error: its message, as tofhil.cli.main prints it
        result = (type(exc).__name__, exc.format_message().replace("Value error, ", ""))
    return result, seen


@pytest.mark.parametrize("args", [
    ["run", "x"],
    ["run", "x", "--size", "2.5", "--count", "7", "--sizes", "0.1", "--sizes", "1", "--tag", "a", "--tag", "b",
     "--where", "/tmp", "--loud"],
    ["run", "x", "--size", "-1"],
    ["run", "x", "--size", "abc"],
    ["run", "x", "--size", "nan"],
    ["run", "x", "--count", "2.5"],
    ["run", "x", "--count", "10"],
    ["run", "x", "--sizes", "0.1", "--sizes", "2"],
    ["run", "x", "--size", "/no/such\x1bfile"],
    ["run"],
    ["other", "--flag"],
])
def test_same_values_and_errors_as_typer(args):
    assert _invoke(args, direct=True) == _invoke(args, direct=False)


@pytest.mark.parametrize("value", ["1", "true", "0", "no", "maybe"])
def test_flag_from_environment_is_typer_s(value):
    # a flag's text from an environment variable goes to typer's own coercion
    env = {"TOFHIL_TEST_LOUD": value}
    assert _invoke(["run", "x"], direct=True, env=env) == _invoke(["run", "x"], direct=False, env=env)


def test_version_still_printed(tofhil_cli):
    import tofhil

    r = tofhil_cli("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"tofhil {tofhil.__version__}"
