"""The typer application, its error policy and small shared helpers for the command modules.

Error policy (docs/design.md section 3.5): a :class:`~topomap.errors.TopomapError` or a command-line usage
error becomes one line on stderr and exit code 1; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import json
import logging
import sys
from typing import Any

import typer
from rich.console import Console
from rich.markup import escape
from typer.core import TyperGroup

from topomap.errors import TopomapError

__all__ = ["app", "console", "err_console", "print_json", "fail"]

#: Results go to stdout; progress, warnings and errors to stderr.
console = Console(highlight=False, soft_wrap=True)
err_console = Console(stderr=True, highlight=False, soft_wrap=True)


def _one_line(msg: str) -> str:
    return " ".join(str(msg).split())


def _is_usage_error(exc: BaseException) -> bool:
    # typer vendors click in recent releases, so match click's exception by its interface rather
    # than importing a private module.
    return hasattr(exc, "format_message") and hasattr(exc, "exit_code") and not isinstance(exc, typer.Exit)


class TopomapGroup(TyperGroup):
    """Root command group: turns expected errors into one line and exit 1."""

    def _guard(self, ctx, call):
        try:
            return call()
        except TopomapError as e:
            fail(str(e))
        except (typer.Exit, typer.Abort):
            raise
        except Exception as e:
            if not _is_usage_error(e):
                raise
            where = getattr(getattr(e, "ctx", None), "command_path", None) or ctx.command_path
            fail(f"{e.format_message()} (see '{where} --help')")

    def make_context(self, info_name, args, parent=None, **extra):
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except (typer.Exit, typer.Abort):
            raise
        except Exception as e:
            if not _is_usage_error(e):
                raise
            fail(f"{e.format_message()} (see '{info_name} --help')")

    def invoke(self, ctx):
        return self._guard(ctx, lambda: super(TopomapGroup, self).invoke(ctx))


def fail(message: str, code: int = 1):
    """Print ``Error: message`` as one line on stderr and exit with ``code``."""
    err_console.print(f"[bold red]Error:[/] {escape(_one_line(message))}", markup=True, highlight=False)
    raise typer.Exit(code)


def print_json(data: Any) -> None:
    """Machine-readable output on stdout (plain, no colour)."""
    sys.stdout.write(json.dumps(data, indent=2, default=_json_default) + "\n")
    sys.stdout.flush()


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    if hasattr(o, "value"):  # enums
        return o.value
    return str(o)


app = typer.Typer(
    cls=TopomapGroup,
    name="topomap",
    help="Map a place from a camera's images and navigate in it from images alone.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


@app.callback()
def _root(
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More log output (-vv for debug)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Only errors."),
) -> None:
    """topomap: appearance topological maps, localization and servoing."""
    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    logger = logging.getLogger("topomap")
    logger.setLevel(level)
    if not any(isinstance(h, _RichLogHandler) for h in logger.handlers):
        logger.addHandler(_RichLogHandler())


class _RichLogHandler(logging.Handler):
    """Library warnings (skipped images, ...) as one dim line each on stderr."""

    def emit(self, record: logging.LogRecord) -> None:
        style = "yellow" if record.levelno >= logging.WARNING else "dim"
        err_console.print(f"[{style}]{record.levelname.lower()}:[/] {escape(_one_line(record.getMessage()))}", markup=True)
