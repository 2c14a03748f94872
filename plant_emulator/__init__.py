"""drivectl.plant_emulator"""
