"""Chains of effect terms, cross-fitted: the velocity-only baseline, then effect terms in
order, each fitted on top of the ones before it on every split's training rows; held-out
(test-row) predictions assembled over the splits.

A chain is a tuple of term names: candidate effects (`effects.EFFECTS`; timing is no term: a
chain holding it is fitted on the table at the timing lag) or `custom` terms (a callable
(table, scales) -> (regressors, names)). `()` is the baseline ("refit"); `("timing",
"drift")` the baseline at the timing lag times the drift term. Fitted baselines and the
states of the chains asked to be kept (`keep`) are cached per split; a candidate's own fit
is not (a forward selection tries several per step).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from egovib_ros.gap import metric
from egovib_ros.gap.baseline import Baseline, fit_baseline
from egovib_ros.gap.effects import FittedModel, Scales, fit_scales, fit_variant
from egovib_ros.gap.features import BlockTable

#: Split index of the fit on every clean block (parameters and shapes for the report).
ALL = -1
#: A term "EFFECT|changed" is the effect's term on the blocks of the recording diagnosed only
#: (`BlockTable.recording`), on a table joining it to a reference recording (gap.change).
CHANGED = "|changed"
#: A term "EFFECT|alone" is the same fitted together with that recording's own level.
ALONE = "|alone"


@dataclass
class Split:
    """One train / test pair of block masks."""

    train: np.ndarray
    test: np.ndarray


@dataclass
class CrossFitted:
    """Out-of-split predictions of the baseline and each candidate, assembled over the splits."""

    predicted: dict[str, np.ndarray]  # name -> (B, F) expected magnitude, valid on test rows
    power: dict[str, np.ndarray]  # name -> (B, F) expected power, valid on test rows
    offset: np.ndarray  # (B, F) baseline training log offset of each row's split
    rows: np.ndarray  # tested rows (sorted)


def as_state(fm: FittedModel, previous: Baseline) -> Baseline:
    """A fitted chain as the baseline the next term is fitted on (the velocity-only
    baseline's cells kept: the per-line interaction needs them)."""
    n_parameters = int(fm.parameters.get("n_parameters", 0))
    return replace(
        previous, magnitude=fm.predicted, power=fm.power, info={"n_parameters": n_parameters}
    )


TermMaker = Callable[[BlockTable, Scales], tuple[np.ndarray, list[str]]]


class ChainFits:
    """Cross-fitted chains of terms on `splits` (see the module's docstring).

    `tables`: {"sync": the table at the in-sync lag, "timing": at the timing lag or None}
    (both with the same contact mask); `clean`: the rows of the fit on every clean block
    (split ALL); `custom`: name -> TermMaker for terms that are no candidate effect."""

    def __init__(
        self,
        tables: dict[str, BlockTable | None],
        splits: list[Split],
        prior,
        *,
        clean: np.ndarray | None = None,
        custom: dict[str, TermMaker] | None = None,
    ):
        self.tables = tables
        self.splits = splits
        self.prior = prior
        self.clean = clean
        self.custom = dict(custom or {})
        self._base: dict[tuple, tuple[Baseline, Scales]] = {}
        self._state: dict[tuple, Baseline] = {}
        self._kept: set[tuple] = set()

    def lag_key(self, chain: tuple[str, ...]) -> str:
        return "timing" if "timing" in chain and self.tables.get("timing") is not None else "sync"

    def table(self, chain: tuple[str, ...]) -> BlockTable:
        return self.tables[self.lag_key(chain)]

    def train(self, k: int) -> np.ndarray:
        return self.clean if k == ALL else self.splits[k].train

    def baseline(self, k: int, key: str) -> tuple[Baseline, Scales]:
        """The velocity-only baseline of split k at lag `key`, and its regressor scales."""
        if (k, key) not in self._base:
            table, train = self.tables[key], self.train(k)
            base = fit_baseline(table, train, prior=self.prior)
            self._base[(k, key)] = (base, fit_scales(table, train, base.magnitude))
        return self._base[(k, key)]

    def keep(self, chain: tuple[str, ...]) -> None:
        """From now on cache the states of `chain` and its prefixes (the chain the next
        candidates are fitted on top of), and only those."""
        terms = self._terms(chain)
        self._kept = {(self.lag_key(chain), terms[:i]) for i in range(len(terms) + 1)}
        self._state = {key: v for key, v in self._state.items() if key[1:] in self._kept}

    def _terms(self, chain: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(e for e in chain if e != "timing")

    def _state_of(self, k: int, key: str, terms: tuple[str, ...]) -> Baseline:
        """The state (as a baseline) after `terms` on split k at lag `key`."""
        if not terms:
            return self.baseline(k, key)[0]
        cached = self._state.get((k, key, terms))
        if cached is not None:
            return cached
        previous = self._state_of(k, key, terms[:-1])
        state = as_state(self._fit_term(k, key, terms[-1], previous), previous)
        if (key, terms) in self._kept:
            self._state[(k, key, terms)] = state
        return state

    def _fit_term(self, k: int, key: str, name: str, previous: Baseline) -> FittedModel:
        table, train = self.tables[key], self.train(k)
        scales = self.baseline(k, key)[1]
        if name in self.custom:
            regressors = self.custom[name](table, scales)
            return fit_variant(table, train, "custom", scales, previous, regressors=regressors)
        for suffix in (CHANGED, ALONE):  # "coupling|changed": the term on one recording only
            if name.endswith(suffix):
                effect, level = name[: -len(suffix)], suffix == ALONE
                mask = table.recording
                return fit_variant(table, train, effect, scales, previous, mask=mask, level=level)
        return fit_variant(table, train, name, scales, previous)

    def fit(self, k: int, chain: tuple[str, ...]) -> FittedModel:
        """The chain's last term (or the refit, for a chain of no terms) fitted on split k
        on top of the ones before it: its predictions for every block, parameters, shape."""
        key, terms = self.lag_key(chain), self._terms(chain)
        if not terms:
            base, scales = self.baseline(k, key)
            return fit_variant(self.tables[key], self.train(k), "refit", scales, base)
        return self._fit_term(k, key, terms[-1], self._state_of(k, key, terms[:-1]))

    def cross(self, chains: dict[str, tuple[str, ...]], *, offset_of: str) -> CrossFitted:
        """Test-row predictions of each named chain over the splits; `offset_of`: the chain
        whose training log offset each row's split gets (the reported log error's centre)."""
        first = next(t for t in self.tables.values() if t is not None)
        n, n_bins = first.magnitude.shape
        observed = first.magnitude
        mags = {name: np.zeros((n, n_bins)) for name in chains}
        pows = {name: np.zeros((n, n_bins)) for name in chains}
        offset = np.zeros((n, n_bins))
        for k, split in enumerate(self.splits):
            test = split.test
            for name, chain in chains.items():
                fm = self.fit(k, chain)
                mags[name][test] = fm.predicted[test]
                pows[name][test] = fm.power[test]
                if name == offset_of:
                    offset[test] = np.mean(
                        metric.block_log_errors(observed[split.train], fm.predicted[split.train]),
                        axis=0,
                    )
        rows = np.flatnonzero(np.any([s.test for s in self.splits], axis=0))
        return CrossFitted(predicted=mags, power=pows, offset=offset, rows=rows)
