"""docs/results.md, generated from bench-results/*.json: every measured number on that page comes from a JSON file.

    python -m haa.lab.results            # write docs/results.md (`make results`)
    python -m haa.lab.results --check    # exit 1 if docs/results.md differs from what would be written

Each benchmark or experiment file has a section of its own, laid out in the thesis' shape where the thesis has
one (Tables 7.1-1, 7.1-2, 7.2-1, 7.2-3, 7.3-1; the statements of §7.2): our figures beside the thesis' values,
with run counts, seeds and spread where the file has them, the file it comes from and the command that
reproduces it. The thesis' values that the files do not carry are constants here, each with the line of the
specification text (seed/000_e446544e9113dd13.txt) it comes from. A file this module does not know gets a
generic section (its top-level scalar fields), so a new result never needs a hand edit.
"""

from haa.lab.results.common import PAGE as PAGE
from haa.lab.results.common import RESULTS_DIR as RESULTS_DIR
from haa.lab.results.page import generate as generate
from haa.lab.results.page import main as main
