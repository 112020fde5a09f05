"""slamkit: a plugin-based RGB-D SLAM framework (GS-ICP SLAM first)."""

__version__ = "0.1.0"
