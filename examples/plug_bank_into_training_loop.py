"""Plug a bank of generated scans into a plain PyTorch training loop: a mean teacher on the bank's scans.

    python examples/plug_bank_into_training_loop.py BANK [--labeled ROOT] [--steps 20] [--seed 0]

BANK is any SemanticKITTI-layout root without labels (what `u4d generate` writes); ROOT, if given, a labelled
root whose scans add a supervised cross-entropy. Each step: a batch of bank scans from a default `DataLoader`
with `collate_scans` (points concatenated, batch index per point, offsets), the student sees them jittered, the
teacher (an EMA of the student) sees them clean, and the loss is the mean-teacher consistency
MSE(softmax student, softmax teacher) (Tarvainen & Valpola 2017). Swap in your own net and losses; the data side
stays these few lines. Seconds on a CPU with the tiny net below.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader

from segmentation import SegModelConfig, build_model, ema_update, make_teacher
from segmentation.mean_teacher import consistency_loss
from u4d_aug import SEMANTICKITTI_IGNORE, ScanDataset, collate_scans, split_points


def batches(root: Path, batch_size: int, seed: int):
    """Endless shuffled batches of a root's scans, collated the sparse-conv way."""
    loader = DataLoader(
        ScanDataset(root),
        batch_size=batch_size,
        shuffle=True,
        collate_fn=collate_scans,
        generator=torch.Generator().manual_seed(seed),
    )
    return itertools.chain.from_iterable(itertools.repeat(loader))


def main(argv: list[str] | None = None) -> int:
    """Train a tiny MinkUNet-like net for a few steps on a bank (and a labelled root); print the losses."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bank", type=Path, help="bank of generated scans (SemanticKITTI layout, no labels)")
    parser.add_argument("--labeled", type=Path, default=None, help="labelled SemanticKITTI-layout root")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--batch-size", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    torch.manual_seed(args.seed)
    student = build_model(SegModelConfig(voxel_size=0.5, width=0.25))
    teacher = make_teacher(student)
    optimizer = torch.optim.AdamW(student.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(args.seed)
    bank = batches(args.bank, args.batch_size, args.seed)
    labeled = batches(args.labeled, args.batch_size, args.seed) if args.labeled else None

    for step in range(1, args.steps + 1):
        batch = next(bank)  # points (N, 4), labels None, batch_index (N,), offsets (B+1,), seq, frame
        scans = split_points(batch)  # B x (N_b, 4): what the segmentation nets take
        jitter = [s + F.pad(0.02 * torch.randn(len(s), 3, generator=generator), (0, 1)) for s in scans]
        with torch.no_grad():
            teacher_logits = teacher(scans)  # (N, K)
        loss = consistency_loss(student(jitter), teacher_logits)
        if labeled is not None:
            real = next(labeled)
            logits = student(split_points(real))
            loss = loss + F.cross_entropy(logits, real["labels"], ignore_index=SEMANTICKITTI_IGNORE)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        ema_update(teacher, student, decay=0.99)
        print(f"step {step}: {len(scans)} bank scans, {len(batch['points'])} points, loss {loss.item():.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
