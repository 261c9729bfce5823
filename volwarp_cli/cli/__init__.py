"""The ``volwarp`` command line (``main.py``: the group; one module per subcommand)."""
