"""``python -m companion``: see ``companion.cli``."""

from companion.cli import main

raise SystemExit(main())
