"""The options of the sampler's moves as plain data: their defaults and their check.

The kernel (``BPHMMKernel(moves=...)``) and the configuration (``SamplerConfig.moves``) read
this one table; ``fit`` turns the warmup's greedy moves on where a configuration does not set
them (``npbrs.inference.driver.fit.DEFAULT_GREEDY_TRIALS``). No JAX here: the configuration is
plain data and imports this module, not the kernel.
"""

from __future__ import annotations

import math

__all__ = ["MOVE_DEFAULTS", "check_moves"]

#: Every option of the kernel's trans-dimensional moves and its value when not given (every move
#: off): trials per sweep of ``birth_death``, ``split_merge``, ``greedy_merge`` and
#: ``greedy_split``; ``window``, the (min, max) steps of a birth's window; ``blocks``, refits of a
#: split's sequential allocation; ``start``, the sweep from which the moves run;
#: ``greedy_from``, the fraction of warmup from which the greedy moves run; ``redraw_unused``, the
#: sweeps between prior redraws of the parameters of skills without steps (1: every sweep; in
#: between they are kept as they are); ``sticky_start``, a factor on a fixed kappa at the first
#: warmup sweep that falls linearly to 1 at mid-warmup (1: off; a search aid of warmup only);
#: ``greedy_patience``: the greedy moves stop for the rest of warmup once no chain has kept one in
#: its last this many greedy sweeps (0: they never stop); ``sticky_phase``, with state-dependent
#: ends, the fraction of warmup whose sweeps search under the sticky BP-HMM (0: none; a search aid
#: of warmup only).
MOVE_DEFAULTS = {"birth_death": 0, "window": (10, 50), "split_merge": 0, "blocks": 2, "start": 0,
                 "greedy_merge": 0, "greedy_split": 0, "greedy_from": 0.75, "redraw_unused": 1,
                 "sticky_start": 1.0, "greedy_patience": 10, "sticky_phase": 0.0}


def check_moves(moves) -> dict:
    """Validated move options with defaults filled in; ValueError naming a bad option."""
    out = dict(MOVE_DEFAULTS)
    for name, value in (moves or {}).items():
        if name not in out:
            raise ValueError(f"unknown move option {name!r}; expected one of {sorted(out)}")
        out[name] = value
    for name in ("birth_death", "split_merge", "greedy_merge", "greedy_split"):
        if not isinstance(out[name], int) or isinstance(out[name], bool) or out[name] < 0:
            raise ValueError(f"moves.{name} must be a number of trials >= 0, got {out[name]!r}")
    if not isinstance(out["blocks"], int) or isinstance(out["blocks"], bool) or out["blocks"] < 1:
        raise ValueError(f"moves.blocks must be an integer >= 1, got {out['blocks']!r}")
    if not isinstance(out["redraw_unused"], int) or isinstance(out["redraw_unused"], bool) or out["redraw_unused"] < 1:
        raise ValueError(f"moves.redraw_unused must be a number of sweeps >= 1, got {out['redraw_unused']!r}")
    p = out["greedy_patience"]
    if not isinstance(p, int) or isinstance(p, bool) or p < 0:
        raise ValueError(f"moves.greedy_patience must be a number of greedy sweeps >= 0 (0: never stop), got {p!r}")
    if not isinstance(out["start"], int) or isinstance(out["start"], bool) or out["start"] < 0:
        raise ValueError(f"moves.start must be a sweep number >= 0, got {out['start']!r}")
    f = out["sticky_start"]
    if isinstance(f, bool) or not isinstance(f, (int, float)) or not (math.isfinite(f) and f >= 1.0):
        raise ValueError(f"moves.sticky_start must be a factor >= 1 on kappa (1: off), got {f!r}")
    out["sticky_start"] = float(f)
    for name in ("greedy_from", "sticky_phase"):
        g = out[name]
        if isinstance(g, bool) or not isinstance(g, (int, float)) or not 0.0 <= g < 1.0:
            raise ValueError(f"moves.{name} must be a fraction of warmup in [0, 1), got {g!r}")
        out[name] = float(g)
    lo, hi = out["window"]
    if not (1 <= int(lo) <= int(hi)):
        raise ValueError(f"moves.window must be (min, max) with 1 <= min <= max, got {out['window']!r}")
    out["window"] = (int(lo), int(hi))
    return out
