"""What a diagnosis may do and what it takes to decide (DiagnoseOptions): the validation
horizon, significance, the screens, the give-ups of fits that cannot change the verdict, pairs,
further starts and processes."""
from __future__ import annotations

import os
from dataclasses import dataclass

from sim.effects import EFFECTS

from ..identify import TRUSTED_VALID


@dataclass(frozen=True)
class DiagnoseOptions:
    candidates: tuple[str, ...] = tuple(EFFECTS)
    horizon_s: float = 1.0  # validation simulation horizon
    min_z: float = 3.0  # z statistic of the validation gain a verdict needs (validation_gain)
    min_shrink: float = 0.02  # ... and this shrink of the all-output validation error
    penalty_per_param: float = 0.01  # shrink charged per added parameter when ranking
    pair: bool = True  # try the best pair when one effect leaves a significant gap
    max_iter: int = 20  # Gauss-Newton iterations of a candidate fit; no wall-clock limit: a fit
    # cut by time would make the verdict depend on the machine's load
    closed_gap: float = 1.2  # a candidate leaving at most this x the noise has closed the gap
    explained: float = 0.5  # a verdict must explain this share of the gap (excess error variance)
    # calibrate the cylinder file's guesses on TRAIN with every candidate (diagnose.calibrated): the
    # nominal calibration is the candidate `none`
    calibrate: bool = False
    # with calibrate: a candidate is calibrated as a whole when its screen (in the stage that sees
    # it) removes this share of that stage's excess above the noise, and screen_share of the best
    # screen's; the `leaders` best of them
    screen_min: float = 0.2
    # ... and the calibration without an effect is given up (status above_reference) once it stays
    # above this multiple of the best screened candidate's calibrated TRAIN cost for
    # IdentifyOptions.give_up_after iterations in a row: it cannot become the better model
    nominal_give_up: float = 1.25
    # ... and a significant candidate whose calibration removes this share of what the calibration
    # without an effect leaves on TRAIN above the noise leaves the lower screens uncalibrated
    train_dominant: float = 0.9
    # ... and a candidate that removes train_explains of what the calibration without an effect
    # leaves on TRAIN above the noise, where that is train_gap x the noise or more, counts when it
    # improves VALID significantly (z) by less than min_shrink: VALID holds what the calibrated
    # model extrapolates to beside the effect (diagnose.calibrated.by_train)
    train_explains: float = 0.5
    train_gap: float = 1.1
    leaders: int = 3  # further starts for this many of the best significant candidates
    # a candidate that explains this share of the gap after the first pass leaves nothing for
    # the other effects' further starts: only its own run (they can only improve its figure)
    dominant: float = 0.98
    # a pair is the verdict when it closes the gap, or when the second effect explains this
    # share of what the first leaves (a partner that imitates part of a single effect's misfit
    # takes less)
    pair_rest: float = 0.8
    # a pair fit that explains less than this share of what it needs to change the verdict
    # (pair_need, of the single effect's excess cost on TRAIN) for IdentifyOptions.give_up_after
    # iterations in a row is given up, not validated
    pair_give_up: float = 0.5
    min_train_gain: float = 1e-3  # a candidate must cut the TRAIN cost by this share to be validated
    # ... and by this share of the best candidate's cut (the screen): what imitates a sliver
    # of the misfit on TRAIN neither wins on VALID nor partners the winner
    screen_share: float = 0.1
    # with calibrate: where the calibration without an effect already reaches VALID within this
    # x the noise, a candidate counts only if one of its effect's parameters lies min_z of its
    # standard deviations from the value that is the nominal plant (shows_itself): on so small
    # a gap any added freedom takes a few percent (an effect-free Norgren on the reference plant:
    # heat exchange at its bound, n 1.5 std from kappa, VALID 1.23 -> 1.15 x)
    small_gap: float = 1.3
    # the model the verdict shows (the nominal one for `none`) predicts VALID within this x the
    # noise, or its predictions carry a caveat (prediction_caveat): where its error lies, and
    # whether TRAIN showed it that regime
    trusted_valid: float = TRUSTED_VALID
    workers: int = max(1, os.cpu_count() or 1)
