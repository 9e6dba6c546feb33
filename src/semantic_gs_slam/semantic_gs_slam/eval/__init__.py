"""Evaluation: metrics and the evaluation of a finished run.

* :mod:`.metrics` — ATE, RPE, PSNR, SSIM, depth L1, mIoU (SSIM is also the mapping loss's).
* :mod:`.metrics_numba` — the compiled CPU SSIM (numba); its kernels in :mod:`.numba_kernels`.
* :mod:`.evaluate` — render every evaluated frame, compare with the dataset, tabulate.
"""
