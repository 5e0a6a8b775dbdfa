"""Option values coerced without pydantic: the commands' own parsers, called directly.

typer 0.29 coerces every parameter through a pydantic ``TypeAdapter``, built when the value is
processed. Importing pydantic (and the ``importlib.metadata`` its plugin loader pulls in) costs
~0.15 CPU-s per process, more than the whole score in ``tofhil ndt`` (timed against PCL as a
whole process). Every tofhil option is a ``parser=`` from :mod:`tofhil.cli.options`, a string
or a flag, and for those the adapter does nothing but call the parser or pass the string
through. :func:`install` gives such parameters a coercion that does exactly that, with typer's
error (``Invalid value for '--x': MESSAGE``); any other kind of parameter or value is left to
typer. The options keep their one definition, in the ``typer.Option`` of each command.

With a typer that has no such hook (before 0.29 it coerced through click's types) nothing is
changed.
"""

from __future__ import annotations

import re
from typing import Any, Callable

__all__ = ["install"]

#: typer escapes terminal control characters in a coercion error (a file name from the user).
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


class _NotMine(Exception):
    """The value is of a kind the direct coercion does not handle: typer's own coercion does."""


def _string(value: object) -> str:
    if isinstance(value, str):
        return value
    raise _NotMine  # bytes from a non-UTF-8 argv: typer decodes them


def _flag(value: object) -> bool:
    if isinstance(value, bool):
        return value
    raise _NotMine  # a flag's text from an environment variable: typer parses it


class _DirectParam:
    """The runtime coercion of one parameter (what typer's ``RuntimeParam`` provides)."""

    __slots__ = ("_item", "_many", "_descriptor", "_typer")

    def __init__(self, item: Callable[[Any], Any], many: bool, descriptor: Any) -> None:
        self._item, self._many, self._descriptor, self._typer = item, many, descriptor, None

    def coerce(self, value: Any, param: Any, ctx: Any) -> Any:
        from typer._click.exceptions import BadParameter

        multi = param.multiple or param.nargs == -1
        if value is None:
            return () if multi else None
        try:
            if multi and isinstance(value, str):
                raise _NotMine  # typer's message for it
            if self._many:
                return [self._item(v) for v in (value if isinstance(value, (list, tuple)) else [value])]
            return self._item(value)
        except _NotMine:
            if self._typer is None:
                from typer._coercion import build_runtime_param

                self._typer = build_runtime_param(self._descriptor)
            return self._typer.coerce(value, param=param, ctx=ctx)
        except ValueError as exc:  # what the options' parsers raise (pydantic's adapter says the same)
            message = _CONTROL.sub(lambda m: f"\\x{ord(m[0]):02x}", str(exc))
            raise BadParameter(message, ctx=ctx, param=param) from None


def _direct_for(param: Any) -> _DirectParam | None:
    from typing import get_args, get_origin

    descriptor = getattr(param, "type_descriptor", None)
    info = getattr(descriptor, "parameter_info", None)
    if info is None or descriptor.file_annotation is not None:
        return None
    annotation, many = descriptor.annotation, False
    if get_origin(annotation) is list:
        (annotation,), many = get_args(annotation), True
    if info.parser is not None:
        return _DirectParam(info.parser, many, descriptor)
    if annotation is str:
        return _DirectParam(_string, many, descriptor)
    if annotation is bool and not many:
        return _DirectParam(_flag, many, descriptor)
    return None  # paths without a parser, numbers without one, choices: typer's coercion


def _typer_has_the_hook() -> bool:
    """The typer internals this module uses are there (they are private: another typer
    release may move them; then typer's own coercion runs, as without this module)."""
    try:
        from typer._click.exceptions import BadParameter  # noqa: F401
        from typer._coercion import build_runtime_param  # noqa: F401
    except ImportError:
        return False
    return True


def install(command: Any, parent: Any = None) -> int:
    """Give every parameter of ``command`` (a click command or group from
    ``typer.main.get_command``) and of its subcommands the direct coercion where it applies;
    return how many parameters got it (0 with a typer that has no such hook)."""
    if parent is None and not _typer_has_the_hook():
        return 0
    # A context as make_context builds it (parent, context_settings): the --help option is
    # made on first use from the context's help option names, and typer coerces it too.
    ctx = command.context_class(command, parent=parent, **command.context_settings)
    done = 0
    for param in command.get_params(ctx):
        if getattr(param, "_runtime_param", False) is None:  # typer builds it on first use
            direct = _direct_for(param)
            if direct is not None:
                param._runtime_param = direct
                done += 1
    for sub in getattr(command, "commands", {}).values():
        done += install(sub, ctx)
    return done
