"""relocalize"""
