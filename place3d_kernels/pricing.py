"""Sensor prices and Pareto fronts of rig quality against cost.

Prices come from a user-editable TOML (``place3d_kernels/configs/prices.toml`` by default: illustrative
list prices, each with its source or marked as an estimate). A rig's cost is the sum of its sensors'
prices; mounting, cabling and compute are not counted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from place3d_kernels._toml import config_dir, read_toml

__all__ = ["DEFAULT_PRICES", "load_prices", "check_prices", "rig_cost", "pareto_front"]

DEFAULT_PRICES = config_dir("lidars").parent / "prices.toml"


def load_prices(path=None) -> dict[str, dict]:
    """``{sensor name: {"price_usd": float, "source": str}}`` from a price TOML (default: the shipped one).

    Raises:
        FileNotFoundError: no such file.
        ValueError: malformed table or a price that is not a non-negative number.
    """
    p = Path(path) if path is not None else DEFAULT_PRICES
    if not p.is_file():
        raise FileNotFoundError(f"price table {str(p)!r} not found; pass a TOML with [sensors.NAME] price_usd = ...")
    d = read_toml(p)
    sensors = d.get("sensors")
    if not isinstance(sensors, dict) or not sensors:
        raise ValueError(f"{p}: needs [sensors.NAME] tables with price_usd (none found)")
    out = {}
    for name, row in sensors.items():
        price = row.get("price_usd") if isinstance(row, dict) else None
        if isinstance(price, bool) or not isinstance(price, (int, float)) or not np.isfinite(price) or price < 0:
            raise ValueError(f"{p}: [sensors.{name}] price_usd must be a non-negative number, got {price!r}")
        out[str(name)] = {"price_usd": float(price), "source": str(row.get("source", ""))}
    return out


def check_prices(prices: dict, sensors, path=None) -> None:
    """Raise ValueError naming every sensor the price table lacks."""
    missing = [s for s in dict.fromkeys(sensors) if s not in prices]
    if missing:
        where = str(path) if path is not None else str(DEFAULT_PRICES)
        raise ValueError(f"price table {where} has no price for sensor(s) {missing}; add [sensors.{missing[0]}] "
                         f"price_usd = ... (or pass --prices FILE)")


def rig_cost(prices: dict, sensors) -> float:
    """Sum of the sensors' prices (US dollars)."""
    check_prices(prices, sensors)
    return float(sum(prices[s]["price_usd"] for s in sensors))


def pareto_front(scores, costs) -> np.ndarray:
    """Indices of the non-dominated points, maximising ``scores`` and minimising ``costs``, ordered by
    cost. A point is dominated when another is no worse in both and better in one; NaN scores never
    enter the front; of exact duplicates the first is kept."""
    s = np.asarray(scores, dtype=np.float64)
    c = np.asarray(costs, dtype=np.float64)
    idx = [i for i in np.argsort(c, kind="stable") if np.isfinite(s[i])]
    front, best = [], -np.inf
    for i in idx:
        if s[i] > best:
            # same cost as the previous front point but better: it dominates that one
            if front and c[front[-1]] == c[i]:
                front.pop()
            front.append(i)
            best = s[i]
    return np.asarray(front, dtype=np.int64)
