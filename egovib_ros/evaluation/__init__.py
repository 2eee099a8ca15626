"""Evaluation: metrics (INTERFACES.md section 6), event detection, baselines, paper experiments.

numpy/scipy only (plus matplotlib with the Agg backend for figures); never rclpy.
"""
