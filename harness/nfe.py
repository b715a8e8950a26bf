"""Counts model forward passes (NFE) from the outside, so a policy cannot under-report.

The counter finds every `torch.nn.Module` reachable from the policy object and hooks
each module inside it. A forward pass is one outermost entry into any of those modules:
calling the whole model counts once, and calling a sub-module directly (to sidestep the
model's own `forward`) counts too. Policies without torch modules count 0.

Torch is never imported here: if the policy made modules, torch is already loaded.
"""

from __future__ import annotations

import sys
from typing import Any

_MAX_DEPTH = 4  # how deep to look through attributes, lists and dicts for modules


def find_modules(obj: Any) -> list[Any]:
    """The torch modules reachable from `obj`, outermost first, without duplicates."""
    torch = sys.modules.get("torch")
    if torch is None:
        return []
    module_type = torch.nn.Module
    found: dict[int, Any] = {}
    seen: set[int] = set()

    def visit(value: Any, depth: int) -> None:
        if id(value) in seen or depth > _MAX_DEPTH:
            return
        seen.add(id(value))
        if isinstance(value, module_type):
            found.setdefault(id(value), value)
            return
        if isinstance(value, dict):
            children = list(value.values())
        elif isinstance(value, (list, tuple, set, frozenset)):
            children = list(value)
        elif hasattr(value, "__dict__") and not isinstance(value, type):
            children = list(vars(value).values())
        else:
            return
        for child in children:
            visit(child, depth + 1)

    visit(obj, 0)
    return list(found.values())


class NFECounter:
    """Forward hooks on every module of a policy; `count` is outermost forward passes."""

    def __init__(self, policy: Any):
        self.count = 0
        self._depth = 0
        self._handles: list[Any] = []
        for root in find_modules(policy):
            for module in root.modules():
                self._handles.append(module.register_forward_pre_hook(self._enter))
                self._handles.append(module.register_forward_hook(self._exit))

    @property
    def hooked_modules(self) -> int:
        return len(self._handles) // 2

    def _enter(self, module: Any, args: Any) -> None:
        if self._depth == 0:
            self.count += 1
        self._depth += 1

    def _exit(self, module: Any, args: Any, output: Any) -> None:
        self._depth -= 1

    def take(self) -> int:
        """Forward passes since the last call; also clears depth left by an exception."""
        count, self.count, self._depth = self.count, 0, 0
        return count

    def close(self) -> None:
        for handle in self._handles:
            handle.remove()
        self._handles.clear()
