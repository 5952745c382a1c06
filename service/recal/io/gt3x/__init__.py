"""ActiGraph ``.gt3x`` files that actfast does not read: ``log.bin`` files whose samples are
ACTIVITY2 records (ActiGraph Link, CentrePoint-era devices) and NHANES-era files
(``activity.bin``), decoded from ActiGraph's published descriptions. ACTIVITY records are read
too, so that the record parsing can be checked against actfast."""

from recal.io.gt3x.reader import Gt3xData, Gt3xReader, read_gt3x, read_gt3x_log

__all__ = ["Gt3xData", "Gt3xReader", "read_gt3x", "read_gt3x_log"]
