"""Augmentation (pipeline steps 3-7): placement, proxies, render, composite, lidar, labels."""
