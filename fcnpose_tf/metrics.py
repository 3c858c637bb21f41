"""Metrics: model cost (MACs) now; PCK, EPE and PCK-AUC join with the training issue. numpy only."""

from __future__ import annotations


def conv_macs(out_h: int, out_w: int, k_h: int, k_w: int, c_in: int, c_out: int) -> int:
    """Multiply-accumulates of one 'same'/'valid' Conv2D for one frame: H*W*k*k*Cin*Cout (FLOPs = 2 x MACs)."""
    return int(out_h) * int(out_w) * int(k_h) * int(k_w) * int(c_in) * int(c_out)
