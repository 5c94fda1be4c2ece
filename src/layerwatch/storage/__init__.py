"""layerwatch.storage"""
