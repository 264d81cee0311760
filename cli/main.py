"""Entry point of the ``topomap`` console script.

Each command module registers its commands on :data:`topomap_cli.app.app` when imported; tests use
``from topomap_cli.main import app`` to get the fully populated application.
"""

from __future__ import annotations

# Command modules (imported for their registrations).
from topomap_cli import build  # noqa: F401
from topomap_cli import localize  # noqa: F401
from topomap_cli import navigate  # noqa: F401
from topomap_cli import observability  # noqa: F401
from topomap_cli import plan  # noqa: F401
from topomap_cli import sim  # noqa: F401
from topomap_cli.app import app

__all__ = ["app", "main"]


def main() -> None:
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
