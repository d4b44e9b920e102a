"""mitsuba"""
