"""Downstream segmentation host: sparse-free voxel nets, LaserMix mean teacher, mIoU/ECE."""
