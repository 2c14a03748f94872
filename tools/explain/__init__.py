"""`drivectl explain`: find where simulation and measurement disagree and name the missing effect.
"""
