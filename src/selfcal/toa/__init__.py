"""selfcal.toa"""
