"""layerwatch.render"""
