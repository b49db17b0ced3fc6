"""selfcal.aoa"""
