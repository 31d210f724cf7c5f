"""`--vary KEY=DIST`: a scene key and the distribution its values are drawn from.

    normal(mu,sigma)          Gaussian with mean mu and standard deviation sigma
    lognormal(median,factor)  ln X ~ N(ln median, ln factor): the geometric standard deviation
                              is `factor`, so 68 % of the values lie in [median/factor,
                              median*factor] and 95 % in [median/factor^1.96, median*factor^1.96]
    uniform(a,b)              uniform on [a, b)
    choice(v1,v2,...)         one of the values, equally likely (numbers or words)

A design (design.py) gives points u in [0, 1)^d; each distribution maps its coordinate to a
value by its inverse CDF (scipy.stats), so Latin-hypercube strata and Sobol points keep their
structure in the values.
"""
import math
import re

import numpy as np
from scipy import stats


class UsageError(Exception):
    """Bad command-line or file input: the tool exits with status 2 and this message."""


_KEY = re.compile(r"^[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)*$")
_DIST = re.compile(r"^\s*([a-z]+)\s*\((.*)\)\s*$")


def format_value(x):
    """A number as `--set` gets it: the shortest text that reads back as the same double, so a
    row of ensemble.csv and a direct run with its values give bit-identical results."""
    return repr(float(x))


class Distribution:
    def __init__(self, key, name, args, text):
        self.key, self.name, self.args, self.text = key, name, args, text

    @property
    def numeric(self):
        return self.name != "choice" or all(_is_number(a) for a in self.args)

    def ppf(self, u):
        """Values for the points u (an array in [0, 1)): floats, or for `choice` its values."""
        u = np.asarray(u, dtype=float)
        if self.name == "choice":
            idx = np.minimum((u * len(self.args)).astype(int), len(self.args) - 1)
            return [self.args[i] for i in idx]
        return self._frozen().ppf(u)

    def quantile(self, q):
        """The exact quantile (continuous distributions): what the tests compare samples with."""
        return float(self._frozen().ppf(q))

    def set_text(self, value):
        """The `--set` argument for one drawn value."""
        v = value if self.name == "choice" else format_value(value)
        return f"{self.key}={v}"

    def _frozen(self):
        a = [float(x) for x in self.args]
        if self.name == "normal":
            return stats.norm(loc=a[0], scale=a[1])
        if self.name == "lognormal":
            return stats.lognorm(s=math.log(a[1]), scale=a[0])
        if self.name == "uniform":
            return stats.uniform(loc=a[0], scale=a[1] - a[0])
        raise ValueError(self.name)

    def to_json(self):
        return {"key": self.key, "distribution": self.name, "parameters": self.args, "text": self.text}


def _is_number(s):
    try:
        float(s)
        return True
    except ValueError:
        return False


# name -> (number of parameters or None for any, checks on the parameters as floats)
_RULES = {
    "normal": (2, lambda a: a[1] > 0 or "sigma must be > 0"),
    "lognormal": (2, lambda a: (a[0] > 0 and a[1] > 1) or "median must be > 0 and factor > 1"),
    "uniform": (2, lambda a: a[0] < a[1] or "needs a < b"),
    "choice": (None, None),
}


def parse_vary(text):
    """`KEY=DIST` -> Distribution; UsageError naming the problem otherwise."""
    key, sep, dist = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise UsageError(f"--vary '{text}': expected KEY=DIST, e.g. tissue.material.young=lognormal(6000,2)")
    if not _KEY.match(key):
        raise UsageError(f"--vary '{text}': '{key}' is not a scene key path (keys joined by '.')")
    m = _DIST.match(dist)
    if not m:
        raise UsageError(f"--vary '{text}': '{dist}' is not NAME(ARGS); distributions: {', '.join(_RULES)}")
    name, body = m.group(1), m.group(2)
    if name not in _RULES:
        raise UsageError(f"--vary '{text}': unknown distribution '{name}'; known: {', '.join(_RULES)}")
    args = [a.strip() for a in body.split(",")] if body.strip() else []
    if any(not a for a in args):
        raise UsageError(f"--vary '{text}': an empty parameter")
    count, check = _RULES[name]
    if name == "choice":
        if not args:
            raise UsageError(f"--vary '{text}': choice needs at least one value")
        return Distribution(key, name, args, dist.strip())
    if len(args) != count:
        raise UsageError(f"--vary '{text}': {name} takes {count} parameters, got {len(args)}")
    bad = [a for a in args if not _is_number(a) or not math.isfinite(float(a))]
    if bad:
        raise UsageError(f"--vary '{text}': parameter '{bad[0]}' is not a finite number")
    verdict = check([float(a) for a in args])
    if verdict is not True:
        raise UsageError(f"--vary '{text}': {name}: {verdict}")
    return Distribution(key, name, args, dist.strip())


def parse_all(texts):
    dists = [parse_vary(t) for t in texts]
    seen = set()
    for d in dists:
        if d.key in seen:
            raise UsageError(f"--vary: key '{d.key}' is given twice")
        seen.add(d.key)
    return dists
