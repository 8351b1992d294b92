"""The verdict: the scored candidates ranked, the best single effect with its runner-up as a
pair, and the rules that name an effect, a pair, `none` or `unexplained`."""
from __future__ import annotations

import copy
import math
from typing import Callable

from ..identify import IdentifyOptions, Validation
from .candidates import (NESTED_START, Candidate, NominalFit, departure_z, explained_share, gain_over, neutral_start,
                         score_candidate)
from .fits import fit_candidate
from .options import DiagnoseOptions


def ranked(cands: list[Candidate], say: Callable[[str], None]) -> tuple[list[Candidate], Candidate | None]:
    """The scored candidates, each said in a line; ranked, the significant ones first by score; and
    the best one when it is significant."""
    for c in cands:
        say(f"  {c.effect:20s} " + (f"shrink {c.shrink:7.1%}  all outputs {c.shrink_all:7.1%}  z {c.z:6.1f}"
                                     if math.isfinite(c.shrink) else f"not scored: {c.error or c.status}"))
    ranking = sorted(cands, key=lambda c: (not c.significant, -c.score))
    return ranking, ranking[0] if ranking and ranking[0].significant else None


# a pair's partner whose every switch-off parameter ends within this many reported standard
# deviations of its neutral value is not there: what the pair gains is the first effect fitted
# better (a strong stiction whose own fit stopped at 42 % of the gap reached 98 % as the pair,
# with the mass at -7.5e-5 +- 4.7e-5)
PARTNER_ABSENT_STD = 2.0


def partner_absent(pair: Candidate) -> bool:
    """Whether the pair's second effect ended at its neutral value (PARTNER_ABSENT_STD)."""
    return departure_z(pair, pair.effect.split("+")[1:]) <= PARTNER_ABSENT_STD


def fold_absent_partner(ranking: list[Candidate], pair: Candidate | None) -> tuple[list[Candidate], Candidate | None, str]:
    """A significant pair whose partner ended at its neutral value (partner_absent) is its first
    effect fitted better: that fit, as the first effect, takes the first effect's place in the
    ranking, and there is no pair. The ranking, the pair left, and a note where it was folded.
    The folded candidate keeps the pair's model (effects, cylinder, nodes: the partner at its
    fitted, neutral value), so that it validates and simulates as fitted; only its name,
    params and std are the first effect's."""
    if pair is None or not pair.significant or pair.validation is None or not partner_absent(pair):
        return ranking, pair, ""
    first, partner = pair.effect.split("+", 1)
    folded = copy.copy(pair)
    folded.effect = first
    folded.params = {k.split(".", 1)[1]: x for k, x in pair.params.items() if k.startswith(first + ".")}
    folded.std = {k.split(".", 1)[1]: x for k, x in pair.std.items() if k.startswith(first + ".")}
    note = (f"{first} as fitted together with {partner}, which ends at its neutral value there (within "
            f"{PARTNER_ABSENT_STD:g} standard deviations): {first}'s fit alone stopped short")
    return [folded if c.effect == first else c for c in ranking], None, note


def with_fold_note(verdict: str, note: str, best: Candidate, folded: str) -> str:
    """The verdict's note: the fold's (fold_absent_partner) where the verdict names the folded
    effect and says nothing else."""
    return note or folded if folded and verdict == best.effect else note


def decide(base: Validation, best: Candidate | None, pair: Candidate | None,
           opts: DiagnoseOptions) -> tuple[str, str]:
    """The verdict and, where it is not simply the best single effect, why.

    - `none`: no candidate improves VALID significantly and the nominal model fits it to near
      the noise (`closed_gap`);
    - `unexplained` also when no candidate improves VALID significantly but a gap above
      `closed_gap` remains;
    - the pair `a+b`: it is significantly better than the best single effect, which alone
      leaves a gap above `closed_gap`, and it closes the gap (to `closed_gap`) or together they
      explain `explained` of the gap and the second effect `pair_rest` of what the first leaves;
      (a pair whose second effect ended at its neutral value is folded into the first effect
      before: fold_absent_partner);
    - `unexplained`: the best candidate (or pair) improves VALID significantly but leaves most
      of a gap that is well above the noise (a weak winner is no diagnosis);
    - otherwise the best single effect."""
    nb = base.normalized_rms()
    if best is None:
        if nb > opts.closed_gap:  # a gap well above the noise that nothing in the vocabulary touches
            return "unexplained", (f"the nominal model misses VALID by {nb:.2f} x the sensor noise over all "
                                   "outputs and no candidate improves it significantly: the gap's cause is not "
                                   "in the vocabulary")
        return "none", ""
    share = explained_share(base, best.validation)
    left = best.validation.normalized_rms()
    if pair is not None and pair.significant and left > opts.closed_gap:
        pshare = explained_share(base, pair.validation)
        # the second effect must itself explain most of what the first leaves, not a sliver
        # of it (a wrong partner imitates part of any remaining error)
        rest = explained_share(best.validation, pair.validation)
        if (pshare >= opts.explained and rest >= opts.pair_rest) or pair.validation.normalized_rms() <= opts.closed_gap:
            return pair.effect, (f"{best.effect} alone explains {share:.0%} of the gap, together with "
                                 f"{pair.effect.split('+')[1]} {pshare:.0%}: both effects are likely present")
        share = max(share, pshare)
    if share < opts.explained and left > opts.closed_gap:
        return "unexplained", (f"the best candidate, {best.effect}, explains only {share:.0%} of the gap (the "
                               f"nominal model misses VALID by {nb:.2f} x the sensor noise over all outputs, "
                               f"{best.effect} by {left:.2f} x): the gap's cause is not in the vocabulary, or "
                               "several effects combine")
    return best.effect, ""


def best_pair(nominal: NominalFit, train, valid, ranking, base_val, base_rmse, segments, opts,
               say) -> Candidate | None:
    """The verdict's effect with the runner-up, when the verdict alone leaves a significant
    gap that the runner-up also addresses. Nested: from the best single fit with the
    runner-up at its neutral value, so never worse than the single effect."""
    best = ranking[0]
    second = next((c for c in ranking[1:] if c.significant), None)
    if second is None or best.validation is None:
        return None
    # a pair can be the verdict only where the best candidate leaves a gap (decide)
    if best.validation.normalized_rms() <= opts.closed_gap:
        return None
    say(f"trying the pair {best.effect} + {second.effect} ...")
    # a fit that stays under pair_give_up of what the pair needs to matter (as a share of the
    # first effect's excess cost on TRAIN) gives up, unvalidated
    need = pair_need(base_val, best.validation, opts)
    excess = best.train_cost - nominal.noise_cost
    give_up = best.train_cost - opts.pair_give_up * need * excess if excess > 0 else math.nan
    inner = NominalFit(nominal.config, nominal.config.with_values(best.friction), best.nodes, best.train_cost,
                       best.validation, nominal.noise_cost, give_up)
    c = fit_candidate((inner, train, valid, (best.effects[0], neutral_start(second.effect)), NESTED_START, opts,
                       segments))
    if c.status == "falls_short":
        c.error = (f"together they explain {(best.train_cost - c.train_cost) / excess:.0%} of what {best.effect} "
                   f"leaves on TRAIN above the sensor noise; to change the verdict the pair needs {need:.0%} of "
                   f"it, and its fit stayed under {opts.pair_give_up * need:.0%} for {IdentifyOptions.give_up_after} "
                   "iterations in a row: given up, not validated")
    score_candidate(c, base_val, base_rmse, opts)
    c.significant = c.significant and gain_over(best.validation, c.validation, opts)
    if math.isfinite(c.shrink):
        say(f"  {c.effect}: shrink {c.shrink:.1%}, all outputs {c.shrink_all:.1%}"
            + ("" if c.significant else " (not significantly better than the verdict alone)"))
    else:
        say(f"  {c.effect}: not scored ({c.error or c.status})")
    return c


def pair_need(base: Validation, best: Validation, opts: DiagnoseOptions) -> float:
    """The share of what the best single effect leaves on VALID (its error variance above the
    noise) that the runner-up must explain for the pair to change the verdict (decide): the
    pair is the verdict where it explains `pair_rest` of it or closes the gap (`closed_gap`),
    and a single effect that explains under `explained` of the gap is named, instead of
    `unexplained`, where the pair lifts that to `explained`. The least of these."""
    b2 = best.normalized_rms() ** 2
    need = min(opts.pair_rest, (b2 - opts.closed_gap ** 2) / (b2 - 1.0))
    share = explained_share(base, best)
    if share < opts.explained:
        need = min(need, (opts.explained - share) / (1.0 - share))
    return max(need, 0.0)
