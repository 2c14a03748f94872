"""drivectl.controllers"""
