"""drivectl.profiles"""
