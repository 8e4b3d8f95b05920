"""Where the tests find the shipped anatomy (../shared/data/heads; see its README.md).

The folder beside the checkout (a worktree may sit one folder deeper), or $JAXHEAD_HEADS. Tests that
need the ANTs head carry `needs_heads` and skip where it is not present.
"""

import os
from pathlib import Path

import pytest

HEADS = Path(os.environ.get("JAXHEAD_HEADS") or next(
    (p / "shared" / "data" / "heads" for p in Path(__file__).resolve().parents
     if (p / "shared" / "data" / "heads").is_dir()), "../shared/data/heads"))
needs_heads = pytest.mark.skipif(not (HEADS / "c1ANTS19-5Years_head.jnii").exists(),
                                 reason="the ANTs test head (../shared/data/heads) is not here")
