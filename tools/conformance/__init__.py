"""Conformance: the drive against canopen's master, the fault matrix and the soak.
"""
