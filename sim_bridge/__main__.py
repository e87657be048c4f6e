"""``python -m sim_bridge {demo,sim}``: see ``sim_bridge.cli``."""

from sim_bridge.cli import main

raise SystemExit(main())
