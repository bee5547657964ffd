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

    def fit_set(self, causes: list[str], warm: Model | None, degree: int = 3, cv: bool = True,
                linear: bool = True) -> Model:
        """Geometry + ``causes`` (strut_nonlinearity of ``degree``; with its gain term when ``linear`` and
        strut_scale is not in)."""
        nl = "strut_nonlinearity" in causes
        linear = bool(linear) and "strut_scale" not in causes
        key = (tuple(causes), degree if nl else 0, linear if nl else True)
        m = self.cache.get(key)
        if m is None:
            keep = self.ctx.nl_degree, self.ctx.nl_linear
            try:
                self.ctx.nl_degree, self.ctx.nl_linear = degree, linear
                r = fit_model(self.cfg, self.ctx, list(causes), self.frame0, self.opts,
                              warm=warm.fit if warm is not None else None)
            finally:
                self.ctx.nl_degree, self.ctx.nl_linear = keep
            r.noise_known = self.known
            m = Model(list(causes), r, bic=bic(r, self.known), nl_degree=degree, nl_linear=linear)
            self.cache[key] = m
        if cv and m.cv_rms != m.cv_rms:   # NaN: not scored yet
            m.cv_rms = cv_score(self.cfg, self.meas, self.ctx, m.fit, m.causes, self.frame0, self.opts)
        return m

    def candidate(self, chosen: list[str], c: str, current: Model) -> Model:
        """chosen + [c]; strut_nonlinearity picks its degree by BIC."""
        if c != "strut_nonlinearity":
            return self.fit_set(chosen + [c], current, current.nl_degree, linear=current.nl_linear)
        # the degree: held-out (CV) evidence first, then BIC among the degrees close to the best CV
        # (a high degree can win the BIC on the fit data and still extrapolate badly between blocks)
        fits = [self.fit_set(chosen + [c], current, d, cv=False) for d in NL_DEGREES]
        # cross-validate the lowest degree and the higher ones whose BIC beats it (cost: CV is 5 fits)
        fits = [m for k, m in enumerate(fits) if k == 0 or m.bic < fits[0].bic - self.opts.min_delta_bic]
        fits = [self.fit_set(m.causes, current, m.nl_degree) for m in fits]
        best_cv = min(m.cv_rms for m in fits)
        return min((m for m in fits if m.cv_rms <= best_cv * (1.0 + self.opts.min_cv_gain)), key=lambda m: m.bic)

    def refit(self, causes: list[str], like: Model, cv: bool = True) -> Model:
        """``causes`` with ``like``'s strut_nonlinearity options."""
        return self.fit_set(causes, like, like.nl_degree, cv=cv, linear=like.nl_linear)

    def passes(self, new: Model, old: Model) -> bool:
        return (old.cv_rms / new.cv_rms >= 1.0 + self.opts.min_cv_gain
                and new.bic - old.bic <= -self.opts.min_delta_bic)


def _entry(m: Model, current: Model, c: str) -> dict:
    e = {"cv_gain": current.cv_rms / m.cv_rms, "delta_bic": m.bic - current.bic, "chi2_red": m.fit.chi2_red,
         "n_parameters": len(m.fit.layout.cause_models[c].names)}
    if c == "strut_nonlinearity":
        e["degree"] = m.nl_degree
    return e


#: (smaller, larger): the smaller model is a part of the larger one (a gain error is the P1 term of the map)
NESTED = (("strut_scale", "strut_nonlinearity"),)


def _nested(a: str, b: str) -> bool:
    return (a, b) in NESTED or (b, a) in NESTED


def forward(sel: Selector, baseline: Model, cands: list[str], table: dict, sig: dict, chi2_limit: float,
            variants: dict) -> tuple[Model, list[str]]:
    opts = sel.opts
    current, chosen = baseline, []
    while len(chosen) < opts.max_causes:
        if sel.known and current.fit.chi2_red <= chi2_limit:
            break
        passing = []
        for c in cands:
            if c in {base_cause(x) for x in chosen}:
                continue
            if c == "strut_scale" and "strut_nonlinearity" in chosen:
                table[c]["verdict"] = "nested in strut_nonlinearity (a gain error is the P1 term of its map)"
                continue
            if (sig["separable_fraction"].get(c) or 0.0) < opts.min_separable_fraction:
                table[c]["verdict"] = "absorbed by geometry: cannot be told apart from a geometric error"
                continue
            passing += _try_candidate(sel, chosen, c, current, table, variants)
        if not passing:
            break
        # the held-out (CV) evidence first: among the candidates close to the best CV residual, the BIC decides
        # (so a nested larger model wins only when the smaller one does not suffice)
        best_cv = min(m.cv_rms for _, m, _ in passing)
        near = [p for p in passing if p[1].cv_rms <= best_cv * (1.0 + opts.min_cv_gain)]
        key, current, entry = min(near, key=lambda p: p[1].bic)
        chosen = chosen + [key]
        b = base_cause(key)
        table[b]["selected_in_round"] = len(chosen)
        table[b]["selected_entry"] = entry
        if key == "strut_nonlinearity" and current.nl_linear and "strut_scale" in cands:
            # the map's gain part is strut_scale: the same model, written so that the re-test checks it apart
            chosen = chosen[:-1] + ["strut_scale", "strut_nonlinearity"]
            current = sel.fit_set(chosen, current, current.nl_degree, linear=False)
            table["strut_scale"]["selected_in_round"] = len(chosen) - 1
            table["strut_scale"]["selected_entry"] = dict(entry, note="the gain (P1) part of strut_nonlinearity's "
                                                                     "map, re-tested on its own")
    return current, chosen


def _try_candidate(sel: Selector, chosen: list[str], c: str, current: Model, table: dict,
                   variants: dict) -> list[tuple[str, Model, dict]]:
    """Fit chosen + c (and its per-strut form); the passing form, if any."""
    m = sel.candidate(chosen, c, current)
    entry = _entry(m, current, c)
    table[c].setdefault("rounds", []).append(entry)
    key, mm, ent = c, m, entry
    v = VARIANTS.get(c) if sel.opts.variants else None
    if v is not None:
        mv = sel.refit(chosen + [v], current)
        ev = _entry(mv, current, v)
        ev["form"] = "per_strut"
        entry["per_strut"] = ev
        if (sel.passes(mv, m) or not sel.passes(m, current)) and sel.passes(mv, current):
            key, mm, ent = v, mv, ev
        variants[c] = variant_evidence(m, mv, key == v)
    return [(key, mm, ent)] if sel.passes(mm, current) else []


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
            without[c] = sel.refit(rest, current) if rest else baseline
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
            m_alt = sel.refit(alt, current)
            common, per = (current, m_alt) if c == b else (m_alt, current)
            use_per = sel.passes(per, common)
            variants[b] = variant_evidence(common, per, use_per)
            variants[b]["in_presence_of"] = [base_cause(x) for x in chosen if x != c]
            if (other == VARIANTS[b]) == use_per and other != c:
                current, chosen = m_alt, alt
                return retest(sel, current, chosen, baseline, dropped, variants)
    return current, chosen, without


def swaps(sel: Selector, current: Model, chosen: list[str], cands: list[str]) -> dict:
    """Per chosen cause: every other candidate in its place, with the BIC change (negative: better)."""
    out = {}
    have = {base_cause(x) for x in chosen}
    for i, c in enumerate(chosen):
        alts = []
        for d in cands:
            if d in have or d == base_cause(c) or _nested(d, base_cause(c)):
                continue
            trial = chosen[:i] + [d] + chosen[i + 1:]
            if d == "strut_scale" and "strut_nonlinearity" in trial:
                continue
            m = sel.refit(trial, current, cv=False)
            alts.append({"name": d, "delta_bic": m.bic - current.bic, "causes": trial,
                         "chi2_red": m.fit.chi2_red if sel.known else None})
        alts.sort(key=lambda a: a["delta_bic"])
        out[c] = alts
    return out


def _better_swap(sel: Selector, current: Model, sw: dict) -> Model | None:
    """A swap that beats the current model by both criteria (the forward search took a stand-in)."""
    for c, alts in sw.items():
        for a in alts:
            if a["delta_bic"] > -sel.opts.min_delta_bic:
                break
            m = sel.refit(a["causes"], current)
            if m.cv_rms <= current.cv_rms:
                return m
    return None


def select(cfg, meas: Measurements, ctx: Context, frame0, opts: Options, known: bool, baseline: Model,
           cands: list[str], table: dict, sig: dict, chi2_limit: float) -> Selection:
    sel = Selector(cfg, meas, ctx, frame0, opts, known)
    sel.cache[((), 0, True)] = baseline
    variants: dict = {}
    current, chosen = forward(sel, baseline, cands, table, sig, chi2_limit, variants)
    dropped: list = []
    current, chosen, without = retest(sel, current, chosen, baseline, dropped, variants)
    sw = swaps(sel, current, chosen, cands)
    for _ in range(3):
        better = _better_swap(sel, current, sw)
        if better is None:
            break
        current, chosen, without = retest(sel, better, list(better.causes), baseline, dropped, variants)
        sw = swaps(sel, current, chosen, cands)
    for c in chosen:
        table[base_cause(c)]["selected_in_round"] = table[base_cause(c)].get("selected_in_round") or -1
    for b in list(variants):
        if b not in {base_cause(x) for x in chosen}:
            variants.pop(b)
    return Selection(current, chosen, table, without, dropped, variants, sw, sel.cache)
