from glob import glob

from setuptools import find_packages, setup

package_name = 'pisc_robust'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_robust']),
        ('share/pisc_robust', ['package.xml']),
        ('share/' + package_name + '/distributions', glob('distributions/*.yaml')),
        ('share/' + package_name + '/distributions/witnesses', glob('distributions/witnesses/*.csv')),
        ('share/' + package_name + '/experiments', glob('experiments/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description='PISC on rigs it was not designed on: parameter distributions, the robustness benchmark, tuning, feasibility, identification, calibration against the thesis experiment, commissioning, the Dask cluster.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'pisc_robustness = pisc_robust.robustness_cli:main',
            'pisc_feasibility = pisc_robust.feasibility_cli:main',
            'pisc_tune = pisc_robust.tune_cli:main',
            'pisc_commission = pisc_robust.commission_cli:main',
            'pisc_calibrate = pisc_robust.calibrate_cli:main',
            'pisc_experiment = pisc_robust.experiment_cli:main',
            'pisc_identify = pisc_robust.identify_cli:main',
        ],
    },
)
