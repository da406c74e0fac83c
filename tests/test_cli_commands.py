"""Every `psimap` subcommand resolves to a function: the CLI has no "not implemented" fallback,
so a registry entry that names a missing module or function must fail here, not at a user's run."""
import importlib

import pytest

from psimap.cli import COMMANDS


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_command_target_is_a_callable(name):
    module, func = COMMANDS[name][1].split(":")
    assert callable(getattr(importlib.import_module(module), func))
