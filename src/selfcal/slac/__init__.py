"""selfcal.slac"""
