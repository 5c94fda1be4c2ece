"""layerwatch.simulate"""
