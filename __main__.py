"""`python -m drivectl`."""

from drivectl.tools.cli.main import main

raise SystemExit(main())
