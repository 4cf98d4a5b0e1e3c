"""Mutual nearest neighbour matching of one query against many references, batched in torch.

Optional spatial ``window`` (pixels), ratio test and minimum cosine similarity; one matrix product per chunk
of references.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from pixie.features import Features, Matches
from pixie.matching.base import RefBank

_NEG = -4.0  # below any cosine similarity: marks pairs that are not candidates


def _as_bank(refs: Sequence[Features] | RefBank, device: torch.device) -> RefBank:
    if isinstance(refs, RefBank):
        return refs
    return RefBank(list(refs), device)


def _pairs_to_matches(
    q_idx: torch.Tensor, ref_idx: torch.Tensor, r_idx: torch.Tensor, sims: torch.Tensor, n_refs: int
) -> list[Matches]:
    """Split flat match lists (sorted by reference) into one :class:`Matches` per reference."""
    q, b, r, s = (t.cpu().numpy() for t in (q_idx, ref_idx, r_idx, sims))
    bounds = np.searchsorted(b, np.arange(n_refs + 1))
    return [Matches(q[x:y], r[x:y], s[x:y]) for x, y in zip(bounds[:-1], bounds[1:])]


def _accept(
    best: torch.Tensor, second: torch.Tensor | None, ratio: float | None, min_sim: float | None
) -> torch.Tensor:
    """Candidate exists, minimum similarity, and ratio test on descriptor distances ``sqrt(2 - 2 s)``."""
    ok = best > _NEG / 2
    if min_sim is not None:
        ok &= best >= min_sim
    if ratio is not None and second is not None:
        d1 = torch.sqrt(torch.clamp(2 - 2 * best, min=0))
        d2 = torch.sqrt(torch.clamp(2 - 2 * second, min=0))
        # a missing second candidate (similarity _NEG) has distance sqrt(10) > 2 and passes
        ok &= d1 < ratio * d2
    return ok


def _mask_window_(sim: torch.Tensor, q_kp: torch.Tensor, q_sqnorm: torch.Tensor, kp: torch.Tensor,
                  sqnorm: torch.Tensor, window: float) -> None:
    """Set the similarities ``sim (b, N, M)`` of keypoint pairs ``window`` px or more apart to ``_NEG``, in place."""
    # squared distances in one fused kernel: |q|^2 + |r|^2 - 2 q.r
    d2 = torch.baddbmm(q_sqnorm[None, :, None] + sqnorm[:, None, :], q_kp[None].expand(sim.shape[0], -1, -1),
                       kp.transpose(1, 2), alpha=-2.0)
    sim.masked_fill_(d2 >= window * window, _NEG)


def _row_best(sim: torch.Tensor, ratio: float | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Best similarity of each query keypoint ``(b, N)``, its column, and the second best (for the ratio test;
    ``None`` without one or with fewer than two columns)."""
    if ratio is not None and sim.shape[2] >= 2:
        top = sim.topk(2, dim=2)
        return top.values[..., 0], top.indices[..., 0], top.values[..., 1]
    best, fwd = sim.max(dim=2)
    return best, fwd, None


def _mnn_chunk(
    q_desc: torch.Tensor,
    q_kp: torch.Tensor,
    q_sqnorm: torch.Tensor,
    desc: torch.Tensor,
    kp: torch.Tensor,
    sqnorm: torch.Tensor,
    valid: torch.Tensor,
    window: float | None,
    ratio: float | None,
    min_sim: float | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mutual NN of one query against a chunk of ``b`` padded references.

    Returns ``(ref_in_chunk, q_idx, r_idx, similarity)`` of the accepted pairs, sorted by reference.
    """
    sim = torch.matmul(q_desc, desc.transpose(1, 2))  # (b, N, M)
    if window is not None:
        _mask_window_(sim, q_kp, q_sqnorm, kp, sqnorm, window)  # padding lies far outside every window
    else:
        sim.masked_fill_(~valid[:, None, :], _NEG)
    best, fwd, second = _row_best(sim, ratio)
    col_best = sim.amax(dim=1)  # (b, M): best similarity of each reference keypoint over the query
    ok = (best >= torch.gather(col_best, 1, fwd)) & _accept(best, second, ratio, min_sim)
    bb, qq = ok.nonzero(as_tuple=True)
    return bb, qq, fwd[bb, qq], best[bb, qq]


def _mnn_dense(
    q_desc: torch.Tensor,
    q_kp: torch.Tensor,
    bank: RefBank,
    window: float | None,
    ratio: float | None,
    min_sim: float | None,
    chunk_elems: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mutual NN against all references of ``bank``, in chunks of about ``chunk_elems`` similarities."""
    pad = bank.padded()
    b_all, m, _ = pad["desc"].shape
    n = q_desc.shape[0]
    per = max(1, chunk_elems // max(1, n * m))
    q_sqnorm = (q_kp.double() ** 2).sum(-1).float()
    out_q, out_b, out_r, out_s = [], [], [], []
    for s0 in range(0, b_all, per):
        sl = slice(s0, s0 + per)
        bb, qq, rr, ss = _mnn_chunk(
            q_desc, q_kp, q_sqnorm, pad["desc"][sl], pad["kp"][sl], pad["sqnorm"][sl], pad["valid"][sl],
            window, ratio, min_sim,
        )
        out_b.append(bb + s0)
        out_q.append(qq)
        out_r.append(rr)
        out_s.append(ss)
    return torch.cat(out_q), torch.cat(out_b), torch.cat(out_r), torch.cat(out_s)


def _row_bands(y: torch.Tensor, height: float) -> list[torch.Tensor]:
    """Indices of the query keypoints in bands of image rows ``height`` tall (empty bands left out)."""
    band = torch.floor((y - y.min()) / height).long()
    order = torch.argsort(band, stable=True)
    ends = torch.cumsum(torch.bincount(band), 0).tolist()
    starts = [0] + ends[:-1]
    return [order[a:b] for a, b in zip(starts, ends) if b > a]


def _mnn_banded(
    q_desc: torch.Tensor,
    q_kp: torch.Tensor,
    bank: RefBank,
    window: float,
    ratio: float | None,
    min_sim: float | None,
    chunk_elems: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_mnn_dense` with a spatial window, computing only the similarities that can fall inside it.

    The query keypoints are split into bands of rows ``window`` tall; with every reference's keypoints sorted
    by row (:meth:`RefBank.padded_by_row`), a band's candidates in a chunk of references lie in one range of
    columns (rows within ``window`` + 1 px of the band), so each band is one smaller product. The window test,
    row maxima, column maxima and the mutual check are those of the dense version: the same matches (the
    products agree to float rounding), at about half the work on object-centred crops.
    """
    pad = bank.padded_by_row()
    b_all, m, _ = pad["desc"].shape
    n = q_desc.shape[0]
    per = max(1, chunk_elems // max(1, n * m))
    q_sqnorm = (q_kp.double() ** 2).sum(-1).float()
    bands = [(qi, q_desc[qi], q_kp[qi], q_sqnorm[qi], q_kp[qi, 1].min(), q_kp[qi, 1].max())
             for qi in _row_bands(q_kp[:, 1], window)]
    reach = window + 1.0
    out_q, out_b, out_r, out_s = [], [], [], []
    for s0 in range(0, b_all, per):
        sl = slice(s0, s0 + per)
        desc, kp, sqnorm, rows_c = pad["desc"][sl], pad["kp"][sl], pad["sqnorm"][sl], pad["rows"][sl]
        b = desc.shape[0]
        best = torch.full((b, n), _NEG)
        second = torch.full((b, n), _NEG) if ratio is not None else None
        fwd = torch.zeros((b, n), dtype=torch.long)
        col_best = torch.full((b, m), _NEG)
        for qi, qd, qk, qs, y0, y1 in bands:
            lo = int(torch.searchsorted(rows_c, (y0 - reach).expand(b, 1).contiguous(), right=True).min())
            hi = int(torch.searchsorted(rows_c, (y1 + reach).expand(b, 1).contiguous()).max())
            if hi <= lo:
                continue
            sim = torch.matmul(qd, desc[:, lo:hi].transpose(1, 2))  # (b, n_band, hi - lo)
            _mask_window_(sim, qk, qs, kp[:, lo:hi], sqnorm[:, lo:hi], window)
            best[:, qi], f, s2 = _row_best(sim, ratio)
            if s2 is not None:
                second[:, qi] = s2
            fwd[:, qi] = f + lo
            col_best[:, lo:hi] = torch.maximum(col_best[:, lo:hi], sim.amax(dim=1))
        ok = (best >= torch.gather(col_best, 1, fwd)) & _accept(best, second, ratio, min_sim)
        bb, qq = ok.nonzero(as_tuple=True)
        out_b.append(bb + s0)
        out_q.append(qq)
        out_r.append(pad["order"][sl][bb, fwd[bb, qq]])
        out_s.append(best[bb, qq])
    return torch.cat(out_q), torch.cat(out_b), torch.cat(out_r), torch.cat(out_s)


def mutual_nn_match_many(
    q: Features,
    refs: Sequence[Features] | RefBank,
    *,
    window: float | None = None,
    ratio: float | None = None,
    min_similarity: float | None = None,
    device: torch.device | str = "cpu",
    chunk_elems: int | None = None,
) -> list[Matches]:
    """Mutual nearest neighbours (cosine similarity) between one query and many references.

    Parameters
    ----------
    q, refs
        The query features and the references (a list, or a prepared :class:`RefBank`). Descriptors are
        expected L2-normalised (every pixie extractor does so).
    window
        Only pairs whose keypoints are closer than ``window`` pixels are candidates (query and references
        share a pixel frame, e.g. equally sized object-centred crops). ``None``: no spatial limit.
    ratio
        Lowe's ratio on descriptor distances among the candidates of one query keypoint in one reference.
    min_similarity
        Minimum cosine similarity of a match.
    device
        Where to compute (a :class:`RefBank` keeps its own device).
    chunk_elems
        Similarities computed per chunk of references (default 2**21 on CPU, 2**26 on CUDA).

    Returns
    -------
    list[Matches]
        One per reference, sorted by query index; scores are cosine similarities.
    """
    bank = _as_bank(refs, torch.device(device))
    dev = bank.device
    if len(bank) == 0:
        return []
    if len(q) == 0 or bank.dim == 0:
        return [Matches.empty() for _ in range(len(bank))]
    if bank.dim != q.dim:
        raise ValueError(f"query descriptors are {q.dim}-D but references are {bank.dim}-D")
    if chunk_elems is None:
        chunk_elems = 1 << (26 if dev.type == "cuda" else 21)
    with torch.inference_mode():
        q_desc = torch.from_numpy(q.descriptors).to(dev)
        q_kp = torch.from_numpy(q.keypoints).to(dev)
        win = None if window is None else float(window)
        if win is not None and dev.type == "cpu":
            res = _mnn_banded(q_desc, q_kp, bank, win, ratio, min_similarity, int(chunk_elems))
        else:
            res = _mnn_dense(q_desc, q_kp, bank, win, ratio, min_similarity, int(chunk_elems))
        return _pairs_to_matches(*res, n_refs=len(bank))


class MutualNNAssigner:
    """Mutual nearest neighbour assignment with optional window / ratio / min similarity."""

    def __init__(
        self,
        device: torch.device,
        *,
        window: float | None = None,
        ratio: float | None = None,
        min_similarity: float | None = None,
    ) -> None:
        self.device = device
        self.window = None if window is None else float(window)
        self.ratio = None if ratio is None else float(ratio)
        self.min_similarity = None if min_similarity is None else float(min_similarity)

    def match_many(self, q: Features, refs: Sequence[Features] | RefBank) -> list[Matches]:
        return mutual_nn_match_many(
            q, refs, window=self.window, ratio=self.ratio, min_similarity=self.min_similarity,
            device=self.device,
        )
