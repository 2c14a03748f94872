"""`python -m drivectl`."""

from drivectl.tools.cli import main

raise SystemExit(main())
