"""``python -m services.cli``: the ``triscan`` command."""

from services.cli import main

raise SystemExit(main())
