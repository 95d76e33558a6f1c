"""benchmarks/diagnostics/consensus_refine.py: the K-draw consensus of one-call x̂0 estimates, checked with an oracle
and a net whose error is pure variance, and run end to end on a tiny net."""

from __future__ import annotations

import pytest
import torch

from tests.tiny_nets import load_script
from u4d_aug.data.formats import read_kitti_scan
from u4d_aug.diffusion import alpha_sigma

bench = load_script("diagnostics/consensus_refine")


def scans(generator: torch.Generator) -> torch.Tensor:
    """(2, 2, 8, 16) range images in [-0.9, 0.9]."""
    return torch.rand((2, 2, 8, 16), generator=generator) * 1.8 - 0.9


def oracle_of(x0: torch.Tensor, jitter: float = 0.0, seed: int = 1):
    """The exact ε of x_t = α x0 + σ ε, plus i.i.d. noise of std `jitter` in x̂0 units on each call."""
    noise = torch.Generator().manual_seed(seed)

    def denoise(x_t, lam, cond):
        alpha, sigma = (float(v) for v in alpha_sigma(lam[0].double()))
        x0_hat = x0 + jitter * torch.randn(x0.shape, generator=noise)
        return (x_t - alpha * x0_hat) / sigma, None

    return denoise


@pytest.mark.parametrize("how", ["mean", "median"])
def test_an_oracle_gives_back_the_scan_and_draws_average_out_a_nets_variance(generator, how):
    x0 = scans(generator)
    exact = bench.consensus(oracle_of(x0), x0, 5.0, 3, how, torch.Generator().manual_seed(0))
    assert torch.allclose(exact, x0, atol=1e-5)
    noisy = oracle_of(x0, jitter=0.05)
    one = (bench.consensus(noisy, x0, 5.0, 1, how, torch.Generator().manual_seed(0)) - x0).abs().mean()
    many = (bench.consensus(noisy, x0, 5.0, 16, how, torch.Generator().manual_seed(0)) - x0).abs().mean()
    assert float(one) == pytest.approx(0.05 * (2 / torch.pi) ** 0.5, rel=0.1)  # E|N(0, s)| = s sqrt(2/π)
    assert float(many) < 0.4 * float(one)  # 16 draws: ~1/4 of the spread (the median's ~1.25x that)
    with pytest.raises(ValueError, match="how must be"):
        bench.consensus(noisy, x0, 5.0, 1, "mode", torch.Generator())


def test_run_writes_every_variant_as_a_scan_folder(untrained_checkpoints, tmp_path):
    out = tmp_path / "refined"
    argv = ["--net", str(untrained_checkpoints["baseline"]), "--num", "2", "--log-snr", "5", "--k", "2",
            "--no-mean-start", "--out", str(out)]  # fmt: skip
    assert bench.main(argv) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["mean_5", "median_5", "none"]
    for name in names:
        files = sorted((out / name / "sequences" / "00" / "velodyne").glob("*.bin"))
        assert [f.name for f in files] == ["000000.bin", "000001.bin"]
        assert read_kitti_scan(files[0]).shape[1] == 4
    assert bench.main(argv) == 2  # its own folder again: not empty, nothing overwritten
    assert bench.main([*argv[:2], "--k", "0", "--out", str(tmp_path / "new")]) == 2
    assert bench.main(["--net", str(untrained_checkpoints["stage2"]), "--out", str(out)]) == 2
