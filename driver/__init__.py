"""drivectl.driver"""
