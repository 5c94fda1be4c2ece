"""layerwatch.evaluate"""
