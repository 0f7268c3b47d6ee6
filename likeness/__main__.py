"""Allow ``python -m likeness``."""

from likeness.cli import main

raise SystemExit(main())
