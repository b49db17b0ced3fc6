"""selfcal.acoustics"""
