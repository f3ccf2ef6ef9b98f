"""``python -m kpcn.report``."""
from .cli import main

raise SystemExit(main())
