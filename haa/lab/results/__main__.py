"""`python -m haa.lab.results`: write (or `--check`) docs/results.md."""

import sys

from haa.lab.results.page import main

sys.exit(main())
