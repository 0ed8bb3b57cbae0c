"""`python -m clients.cli ...` is the `govnesf` command."""

from clients.cli import main

raise SystemExit(main())
