"""layerwatch.web"""
