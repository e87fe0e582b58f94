"""Statistics of the MASAT paper-reproduction studies (not part of the rgbdslam package):
the paper comparison as a table, and paired (McNemar) comparisons of two initial guesses on the
same instances. Used by compare_to_paper.py beside this file; the
benchmark protocol itself is ``rgbdslam.posegraph.bench`` (``rgbdslam posegraph bench``).
"""

from __future__ import annotations

from rgbdslam.posegraph.bench import METHOD_NAMES, at_optimum, level_index, noise_text


def format_paper_comparison(rows: list[dict]) -> str:
    out = ["| noise | start | ours k/n | rate [95 % Wilson] | paper (column) | Fisher p | verdict | Holm p | "
           "verdict (Holm) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        col = "" if r["paper_column"] == r["method"] else f" ({METHOD_NAMES[r['paper_column']]})"
        out.append(f"| {noise_text(r['sigma'])} | {METHOD_NAMES[r['method']]} | {r['k']}/{r['n']} | "
                   f"{r['rate']:.2f} [{r['lo']:.2f}, {r['hi']:.2f}] | {r['paper']:.2f}{col} | {r['p']:.3f} | "
                   f"{r['verdict']} | {r['p_holm']:.3f} | {r['verdict_holm']} |")
    return "\n".join(out)


def paired_comparison(records, a: str, b: str, alpha: float = 0.05, criterion: str = "relative") -> list[dict]:
    """Per noise level: exact McNemar test of start ``a`` against start ``b`` on the same instances,
    for "converged" and for "converged to the optimum" (final χ² within :data:`OPTIMUM_RTOL` of GT + GN's;
    ``None`` without ground-truth runs).  Of the instances where exactly one of the two converged,
    ``only_a`` were ``a``'s; p is the two-sided binomial test of ``only_a`` against half of them."""
    from scipy.stats import binomtest

    by = {(r.sigma_x, r.sigma_y, r.sigma_theta, r.instance, r.method): r for r in records}
    rows = []
    for sigma in sorted({(r.sigma_x, r.sigma_y, r.sigma_theta) for r in records}, key=lambda s: (level_index(s), s)):
        inst = sorted(k[3] for k in by if k[:3] == sigma and k[4] == a and (*sigma, k[3], b) in by)
        if not inst:
            continue
        row = dict(sigma=sigma, n=len(inst))
        for what in ("converged", "optimum"):
            def ok(r, what=what):
                conv, _, rchi2 = r.verdict(criterion)
                if what == "converged":
                    return conv
                g = by.get((*sigma, r.instance, "ground_truth"))
                return None if g is None else at_optimum(conv, rchi2, g.verdict(criterion)[2])
            va = [ok(by[(*sigma, i, a)]) for i in inst]
            vb = [ok(by[(*sigma, i, b)]) for i in inst]
            if any(v is None for v in va + vb):
                row[what] = None
                continue
            only_a = sum(x and not y for x, y in zip(va, vb))
            only_b = sum(y and not x for x, y in zip(va, vb))
            p = 1.0 if only_a + only_b == 0 else float(binomtest(only_a, only_a + only_b, 0.5).pvalue)
            verdict = "same" if p >= alpha else (f"{a} better" if only_a > only_b else f"{b} better")
            row[what] = dict(rate_a=sum(va) / len(va), rate_b=sum(vb) / len(vb), only_a=only_a, only_b=only_b,
                             p=p, verdict=verdict)
        rows.append(row)
    return rows


def format_paired(rows: list[dict], a: str, b: str) -> str:
    na, nb = METHOD_NAMES.get(a, a), METHOD_NAMES.get(b, b)
    out = [f"| noise | n | converged {na} / {nb} | only {na} / only {nb} | McNemar p | "
           f"at optimum {na} / {nb} | only {na} / only {nb} | McNemar p |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = []
        for what in ("converged", "optimum"):
            c = r[what]
            cells += ["–", "–", "–"] if c is None else [f"{c['rate_a']:.2f} / {c['rate_b']:.2f}",
                                                       f"{c['only_a']} / {c['only_b']}", f"{c['p']:.3f}"]
        out.append(f"| {noise_text(r['sigma'])} | {r['n']} | " + " | ".join(cells) + " |")
    return "\n".join(out)
