"""`python -m usvc.cli`: the `usvc` command."""

import sys

from usvc.cli import main

sys.exit(main())
