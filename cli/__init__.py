"""The ``topomap`` command line: a thin typer layer over the :mod:`topomap` library."""
