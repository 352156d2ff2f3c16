"""msdnet.export"""
