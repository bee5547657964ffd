"""Cause selection: forward search, per-strut variants, re-test in the presence of the others, swaps.

1. Forward: a candidate joins when it improves the blocked cross-validated
   residual by more than ``min_cv_gain`` and the Bayesian information criterion
   by more than ``min_delta_bic`` (and, with a known noise, while the model's
   chi^2 is significantly above the noise).  A cause with a per-strut form
   (:data:`~hexacnc.calib.model.VARIANTS`) is fitted in both forms; the
   per-strut form is taken only when it beats the common one by the same two
   criteria (or when only it passes).
2. Re-test: each named cause is removed in turn from the final model; the
   weakest is dropped when the model without it is not significantly worse
   (same two criteria), until every cause earns its place.  Each cause's own
   gain in the presence of the others is kept (CV and, later, held-out).
   The per-strut / common choice is re-made in the presence of the others.
3. Swaps: each named cause is replaced by each other applicable candidate; when
   a swap costs less than ``min_swap_delta_bic`` the data cannot tell the two
   apart (reported as inseparable, not named).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from .fitting import NL_DEGREES, Model, Options, bic, cv_score, fit_model
from .measurements import Measurements
from .model import VARIANTS, Context, base_cause


@dataclass
class Selection:
    model: Model                                   #: the final extended model
    chosen: list[str]                              #: its cause models (layout keys, variants included)
    table: dict                                    #: per catalog candidate: applicability, rounds, verdicts
    without: dict = field(default_factory=dict)    #: per chosen key: the final model without it
    dropped: list = field(default_factory=list)    #: causes dropped on re-test, with the evidence
    variants: dict = field(default_factory=dict)   #: per catalog cause with a per-strut form: the evidence
    swaps: dict = field(default_factory=dict)      #: per chosen key: alternatives and their BIC cost
    fits: dict = field(default_factory=dict)       #: every model fitted on the way, by (causes, degree)


class Selector:
    """Fits cause sets of one data set (cached), and runs the selection."""

    def __init__(self, cfg, meas: Measurements, ctx: Context, frame0, opts: Options, known: bool):
        self.cfg, self.meas, self.ctx, self.frame0, self.opts, self.known = cfg, meas, ctx, frame0, opts, known
        self.cache: dict = {}

    def fit_set(self, causes: list[str], warm: Model | None, degree: int = 3, cv: bool = True) -> Model:
        """Geometry + ``causes`` (strut_nonlinearity of ``degree``; its gain term unless strut_scale is in)."""
        key = (tuple(causes), degree if "strut_nonlinearity" in causes else 0)
        m = self.cache.get(key)
        if m is None:
            keep = self.ctx.nl_degree, self.ctx.nl_linear
            try:
                self.ctx.nl_degree, self.ctx.nl_linear = degree, "strut_scale" not in causes
                r = fit_model(self.cfg, self.ctx, list(causes), self.frame0, self.opts,
                              warm=warm.fit if warm is not None else None)
            finally:
                self.ctx.nl_degree, self.ctx.nl_linear = keep
            r.noise_known = self.known
            m = Model(list(causes), r, bic=bic(r, self.known), nl_degree=degree)
            self.cache[key] = m
        if cv and m.cv_rms != m.cv_rms:   # NaN: not scored yet
            m.cv_rms = cv_score(self.cfg, self.meas, self.ctx, m.fit, m.causes, self.frame0, self.opts)
        return m

    def candidate(self, chosen: list[str], c: str, current: Model) -> Model:
        """chosen + [c]; strut_nonlinearity picks its degree by BIC."""
        if c != "strut_nonlinearity":
            return self.fit_set(chosen + [c], current, current.nl_degree)
        fits = [self.fit_set(chosen + [c], current, d, cv=False) for d in NL_DEGREES]
        best = min(fits, key=lambda m: m.bic)
        return self.fit_set(best.causes, current, best.nl_degree)

    def passes(self, new: Model, old: Model) -> bool:
        return (old.cv_rms / new.cv_rms >= 1.0 + self.opts.min_cv_gain
                and new.bic - old.bic <= -self.opts.min_delta_bic)


def _entry(m: Model, current: Model, c: str) -> dict:
    e = {"cv_gain": current.cv_rms / m.cv_rms, "delta_bic": m.bic - current.bic, "chi2_red": m.fit.chi2_red,
         "n_parameters": len(m.fit.layout.cause_models[c].names)}
    if c == "strut_nonlinearity":
        e["degree"] = m.nl_degree
    return e


def forward(sel: Selector, baseline: Model, cands: list[str], table: dict, sig: dict, chi2_limit: float,
            variants: dict) -> tuple[Model, list[str]]:
    opts = sel.opts
    current, chosen = baseline, []
    while len(chosen) < opts.max_causes:
        if sel.known and current.fit.chi2_red <= chi2_limit:
            break
        have = {base_cause(x) for x in chosen}
        best = None
        for c in cands:
            if c in have:
                continue
            if c == "strut_scale" and "strut_nonlinearity" in chosen:
                table[c]["verdict"] = "nested in strut_nonlinearity (a gain error is the P1 term of its map)"
                continue
            if (sig["separable_fraction"].get(c) or 0.0) < opts.min_separable_fraction:
                table[c]["verdict"] = "absorbed by geometry: cannot be told apart from a geometric error"
                continue
            m = sel.candidate(chosen, c, current)
            entry = _entry(m, current, c)
            table[c].setdefault("rounds", []).append(entry)
            key, mm = c, m
            v = VARIANTS.get(c) if opts.variants else None
            if v is not None:
                mv = sel.fit_set(chosen + [v], current, current.nl_degree)
                ev = _entry(mv, current, v)
                ev["form"] = "per_strut"
                entry["per_strut"] = ev
                if (sel.passes(mv, m) or not sel.passes(m, current)) and sel.passes(mv, current):
                    key, mm = v, mv
                variants[c] = variant_evidence(m, mv, key == v)
            if sel.passes(mm, current) and (best is None or mm.bic < best[1].bic):
                best = (key, mm)
        if best is None:
            break
        chosen.append(best[0])
        table[base_cause(best[0])]["selected_in_round"] = len(chosen)
        current = best[1]
    return current, chosen


def variant_evidence(common: Model, per: Model, chosen_per: bool) -> dict:
    return {"chosen": "per_strut" if chosen_per else "common",
            "cv_whitened_rms": {"common": common.cv_rms, "per_strut": per.cv_rms},
            "cv_gain_per_strut_over_common": common.cv_rms / per.cv_rms,
            "bic": {"common": common.bic, "per_strut": per.bic},
            "delta_bic_per_strut_minus_common": per.bic - common.bic,
            "rule": "per strut when it lowers the CV residual by the minimum gain and the BIC by the minimum delta"}


def retest(sel: Selector, current: Model, chosen: list[str], baseline: Model, dropped: list,
           variants: dict) -> tuple[Model, list[str], dict]:
    """Drop causes that no longer earn their place; re-choose per-strut / common forms; own gains."""
    while True:
        without = {}
        for c in chosen:
            rest = [x for x in chosen if x != c]
            without[c] = sel.fit_set(rest, current, current.nl_degree) if rest else baseline
        if len(chosen) < 2 or not sel.opts.retest:
            break
        weakest = min(chosen, key=lambda c: without[c].cv_rms / current.cv_rms)
        if sel.passes(current, without[weakest]):
            break
        dropped.append({"name": base_cause(weakest), "model": weakest,
                        "cv_gain_in_presence_of_others": without[weakest].cv_rms / current.cv_rms,
                        "delta_bic_in_presence_of_others": current.bic - without[weakest].bic,
                        "reason": "no longer improves the held-out (CV) residual and the BIC significantly "
                                  "once the other causes are in the model"})
        current, chosen = without[weakest], [x for x in chosen if x != weakest]
    if sel.opts.variants and len(chosen) >= 2:
        for i, c in enumerate(list(chosen)):
            b = base_cause(c)
            if b not in VARIANTS:
                continue
            other = VARIANTS[b] if c == b else b
            alt = chosen[:i] + [other] + chosen[i + 1:]
            m_alt = sel.fit_set(alt, current, current.nl_degree)
            common, per = (current, m_alt) if c == b else (m_alt, current)
            use_per = sel.passes(per, common)
            variants[b] = variant_evidence(common, per, use_per)
            variants[b]["in_presence_of"] = [base_cause(x) for x in chosen if x != c]
            if (other == VARIANTS[b]) == use_per and other != c:
                current, chosen = m_alt, alt
                return retest(sel, current, chosen, baseline, dropped, variants)
    return current, chosen, without


def swaps(sel: Selector, current: Model, chosen: list[str], cands: list[str]) -> dict:
    """Per chosen cause: every other candidate that explains the data about as well in its place."""
    out = {}
    have = {base_cause(x) for x in chosen}
    for i, c in enumerate(chosen):
        alts = []
        for d in cands:
            if d in have or d == base_cause(c):
                continue
            trial = chosen[:i] + [d] + chosen[i + 1:]
            if d == "strut_scale" and "strut_nonlinearity" in trial:
                continue
            m = sel.fit_set(trial, current, current.nl_degree, cv=False)
            alts.append({"name": d, "delta_bic": m.bic - current.bic,
                         "chi2_red": m.fit.chi2_red if sel.known else None})
        alts.sort(key=lambda a: a["delta_bic"])
        out[c] = alts
    return out


def select(cfg, meas: Measurements, ctx: Context, frame0, opts: Options, known: bool, baseline: Model,
           cands: list[str], table: dict, sig: dict, chi2_limit: float) -> Selection:
    sel = Selector(cfg, meas, ctx, frame0, opts, known)
    sel.cache[((), 0)] = baseline
    variants: dict = {}
    current, chosen = forward(sel, baseline, cands, table, sig, chi2_limit, variants)
    dropped: list = []
    current, chosen, without = retest(sel, current, chosen, baseline, dropped, variants)
    sw = swaps(sel, current, chosen, cands)
    for b in list(variants):
        if b not in {base_cause(x) for x in chosen}:
            variants.pop(b)
    return Selection(current, chosen, table, without, dropped, variants, sw, sel.cache)
