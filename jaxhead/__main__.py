"""`python -m jaxhead ...` is the `jaxhead` command."""

import sys

from .cli import main

sys.exit(main())
