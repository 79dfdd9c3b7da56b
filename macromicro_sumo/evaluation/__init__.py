"""Evaluation: methods and baselines, rollouts, statistics, leader-follower tests."""
