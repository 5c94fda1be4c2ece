"""layerwatch.monitor.printers"""
