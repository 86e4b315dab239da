"""OmegaConf resolvers our configs use; registered when `framework` is imported (Hydra imports it to compose).

`${scaled:VALUE,NUM,DEN}` is VALUE * NUM / DEN, an int when VALUE is an int (rounded). Profiles use it to state a
schedule once in the paper's terms and let one knob stretch it, e.g. `first_reset: ${scaled:3000,${.max_steps},30000}`
is "the paper's step 3000 of 30000, at this profile's length"; the studio's realistic preset scales pixel widths with
the resolution the same way.
"""

from __future__ import annotations

from omegaconf import OmegaConf


def scaled(value: int | float, numerator: int | float, denominator: int | float) -> int | float:
    if float(denominator) == 0.0:
        raise ValueError(f"${{scaled:{value},{numerator},{denominator}}}: the denominator must not be 0.")
    out = float(value) * float(numerator) / float(denominator)
    return int(round(out)) if isinstance(value, int) else out


def register() -> None:
    """Idempotent: safe to call from every entry point and test."""
    if not OmegaConf.has_resolver("scaled"):
        OmegaConf.register_new_resolver("scaled", scaled)


register()
