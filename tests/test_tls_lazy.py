"""A host without TLS does not load `cryptography` (~13 MiB of RSS per host process,
measured): haa.tls imports it where a certificate is read."""

from __future__ import annotations

import subprocess
import sys


def test_the_daemon_imports_no_cryptography_until_tls_is_used() -> None:
    code = (
        "import sys, haa.hostd.daemon\n"
        "print('cryptography' in sys.modules)\n"
        "from haa import tls\n"
        "tls.parse_identity('urn:haa:host:h1')\n"
        "print('cryptography' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False"]
