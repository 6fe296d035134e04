"""``python -m eyeserver``: the same as the ``eyeserver`` command."""

from eyeserver.cli import main

raise SystemExit(main())
