"""layerwatch.gcode"""
