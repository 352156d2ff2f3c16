"""msdnet.runtime"""
