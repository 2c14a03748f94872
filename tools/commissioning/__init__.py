"""Commissioning: scan/status/enable commands, identification, Bode, tuning and learning.
"""
