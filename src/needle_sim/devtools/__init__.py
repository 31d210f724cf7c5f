"""Tools for the source tree: doc/scene_format.md's key tables (scene_keys_doc, a CTest
check), the behaviour regression of every shipped scene before and after a refactor
(scene_regression)."""
