"""u4d-aug: uncertainty-aware 4D LiDAR scene synthesis (U4D) as a segmentation data-augmentation plugin."""

__version__ = "0.1.0"
