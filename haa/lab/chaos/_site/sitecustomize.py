"""Imported by Python at start-up when this directory is on PYTHONPATH (haa.lab.chaos.mutations.mutation_env): in
a haa-hostd process, apply the chaos mutation HAA_CHAOS_MUTATION names.
Any other process is left alone."""

import os

if os.environ.get("HAA_CHAOS_MUTATION"):
    from haa.lab.chaos.mutations import apply_from_env

    apply_from_env()
