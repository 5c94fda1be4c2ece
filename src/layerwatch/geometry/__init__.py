"""layerwatch.geometry"""
