"""Readers of LES cloud fields and synthetic data for cloudct."""
