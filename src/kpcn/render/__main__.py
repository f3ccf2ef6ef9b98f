"""``python -m kpcn.render``: see :mod:`kpcn.render.cli`."""
from .cli import main

raise SystemExit(main())
