"""Where the tests find the shipped anatomy (../shared/data/heads; see its README.md).

The folder beside the checkout (a worktree may sit one folder deeper), or $JAXHEAD_HEADS. Tests that
need the ANTs head carry `needs_heads` and skip where it is not present.
"""

import pytest

from jaxhead.segmentation.templates import shipped_heads_folder

HEADS = shipped_heads_folder()
needs_heads = pytest.mark.skipif(not (HEADS / "c1ANTS19-5Years_head.jnii").exists(),
                                 reason="the ANTs test head (../shared/data/heads) is not here")
