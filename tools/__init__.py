"""drivectl.tools"""
