"""layerwatch.analysis"""
