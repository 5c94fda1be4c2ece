"""layerwatch.monitor"""
