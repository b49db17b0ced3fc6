"""selfcal.tdoa"""
