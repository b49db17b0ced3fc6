"""selfcal.scenarios"""
