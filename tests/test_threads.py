"""psimap.threads.single_threaded: one torch and one native thread inside, the old counts after."""
from __future__ import annotations

import pytest
import torch

from psimap.threads import single_threaded


def test_single_threaded_sets_and_restores_even_on_error():
    native = pytest.importorskip("psimap.render.native")
    t0, n0 = torch.get_num_threads(), native.get_num_threads()
    torch.set_num_threads(2)
    native.set_num_threads(2)
    try:
        with single_threaded():
            assert torch.get_num_threads() == 1 and native.get_num_threads() == 1
        assert torch.get_num_threads() == 2 and native.get_num_threads() == 2
        with pytest.raises(ValueError), single_threaded():
            raise ValueError("boom")
        assert torch.get_num_threads() == 2 and native.get_num_threads() == 2
    finally:
        torch.set_num_threads(t0)
        native.set_num_threads(n0)
