from glob import glob

from setuptools import find_packages, setup

package_name = 'pisc_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_bringup']),
        ('share/pisc_bringup', ['package.xml']),
        ('share/' + package_name + '/distributions', glob('distributions/*.yaml')),
        ('share/' + package_name + '/experiments', glob('experiments/*.yaml')),
        ('share/' + package_name + '/distributions/witnesses',
         glob('distributions/witnesses/*.csv')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.xml')),
        ('share/' + package_name + '/config', glob('config/*.xml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description='PISC graph runner, recorder, run summary and parameter files.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'markers_node = pisc_bringup.markers_node:main',
            'pisc_foxglove = pisc_bringup.foxglove_node:main',
            'pisc_graph = pisc_bringup.graph:main',
            'pisc_record = pisc_bringup.record:main',
            'pisc_integrators = pisc_bringup.integrators_cli:main',
            'pisc_scene = pisc_bringup.scene_cli:main',
            'pisc_batch_bench = pisc_bringup.batch_bench:main',
            'pisc_bag = pisc_bringup.bag_cli:main',
            'pisc_robustness = pisc_bringup.robustness_cli:main',
            'pisc_feasibility = pisc_bringup.feasibility_cli:main',
            'pisc_tune = pisc_bringup.tune_cli:main',
            'pisc_commission = pisc_bringup.commission_cli:main',
            'pisc_commission_bench = pisc_bringup.commission_bench:main',
            'pisc_calibrate = pisc_bringup.calibrate_cli:main',
            'pisc_experiment = pisc_bringup.experiment_cli:main',
            'pisc_identify = pisc_bringup.identify_cli:main',
            'pisc_soak = pisc_bringup.soak:main',
            'pisc_bench = pisc_bringup.bench:main',
            'pisc_parser_bench = pisc_bringup.parser_bench:main',
        ],
    },
)
