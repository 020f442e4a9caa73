"""The paper's numbers (SPI-BoTER, UR5, 724 samples, test split; docs/method.md, Tables 4-9): the one place they live."""

PAPER_TEST = {"x": {"mae": 0.1110, "mse": 0.0213, "rmse": 0.1461, "r2": 0.9682},
              "y": {"mae": 0.1537, "mse": 0.0379, "rmse": 0.1947, "r2": 0.8822},
              "z": {"mae": 0.1135, "mse": 0.0220, "rmse": 0.1484, "r2": 0.9612},
              "3d": {"mae": 0.2515, "mse": 0.0812, "rmse": 0.2850, "r2": 0.9479}}
PAPER_METHODS = {"DNN": {"mae": 0.3880, "rmse": 0.4386, "r2": 0.8787},
                 "GPSO-DNN": {"mae": 0.3405, "rmse": 0.3840, "r2": 0.9070},
                 "SPI-BoTER": {"mae": 0.2515, "rmse": 0.2850, "r2": 0.9479}}
PAPER_METHOD_OF = {"dnn": "DNN", "spi_boter_nominal": "SPI-BoTER"}   # our name -> paper row
PAPER_ABLATION = {"baseline": 0.2515, "data_only": 0.2880, "no_mask": 0.2756,
                  "body_mask": 0.2911, "no_resnet": 0.3128, "no_transformer": 0.3072}
PAPER_ABLATION_EPOCHS = {"baseline": 111, "no_mask": 402, "body_mask": 103, "no_resnet": 304,
                         "no_transformer": 341}
PAPER_DRIVE = {"x": {"std": 0.1355, "max": 0.4850, "min": 0.0010},      # Table 9, 50 points
               "y": {"std": 0.1438, "max": 0.7240, "min": 0.0260},
               "z": {"std": 0.1314, "max": 0.8220, "min": 0.0030}}
PAPER_DRIVE_WITHIN = "48/50 = 96 % (the text says 98 %)"
